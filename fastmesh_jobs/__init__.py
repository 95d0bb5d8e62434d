"""The job system the HTTP service and the workers share: the Redis store (``store``: one ``Store`` over the job
states, blobs, workers, limits, idempotency keys and telemetry, each a module of its own), the reaper of lost and
overdue jobs (``reaper``), the ``FASTMESH_*`` settings (``settings``) and what a worker and its supervisor agree
on at run time (``runtime``)."""
