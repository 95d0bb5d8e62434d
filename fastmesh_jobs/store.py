"""Jobs, inputs and results in Redis; shared by the API and the workers.

:class:`Store` is one object over one Redis connection; each concern is a class of its own module that owns its
keys (``P`` is ``Settings.redis_prefix``)::

    states       P:job:<id> P:hb:<id> P:running P:queued P:owned:<owner> P:webhooks
                 the job hash and its compare-and-set transitions: submit, start, progress, finish, cancel,
                 requeue, delete; how ``GET /v1/jobs/{id}`` shows a job
    blobs        P:input:<id> P:result:<id>:<fmt> P:preview:<id>
                 a job's input, results and previews, and the npz they are stored as
    workers      P:workers P:worker:<name> P:vertex_limit
                 worker heartbeats and registrations, the vertex limit of their models
    limits       P:rate:<kind>:<owner>:<minute> P:authok:<address>:<owner>
                 per-minute request windows, the authentication lockout, admission to the queue
    idempotency  P:idem:<owner>:<sha>
                 which job an Idempotency-Key names (the protocol is ``service.idempotency``)
    telemetry    P:stats:jobs P:stats:stage:<stage> P:stats:distance:<cd|hd>
                 job counters and histograms for ``/metrics``

``P:suspects`` (job id -> when its queue entry was first seen missing) is the reaper's (``reaper``).  Each
module's docstring holds the layout of its keys.
"""

from __future__ import annotations

from .idempotency import IdempotencyKeys
from .states import JobStates
from .workers import WorkerRegistry


class Store(JobStates, WorkerRegistry, IdempotencyKeys):
    """Redis access for one settings object: :class:`~fastmesh_jobs.part.StorePart` (settings, connection, queue)
    with every concern's methods (``JobStates`` brings the blobs, telemetry and limits it builds on).
    Thread-safe (redis-py pools connections)."""
