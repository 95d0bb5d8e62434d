"""The job system the HTTP service and the workers share: the Redis store of jobs, batches, blobs, workers and
limits (``store``), the reaper of lost and overdue jobs (``reaper``), the ``FASTMESH_*`` settings (``settings``)
and what a worker and its supervisor agree on at run time (``runtime``)."""
