"""The ``Idempotency-Key`` protocol of ``POST /v1/jobs``: a retried submission gets the job the first one made.

Redis keeps, per owner and key, ``"<job id> <fingerprint>"`` (:meth:`fastmesh_jobs.store.Store.idempotency_get`);
the fingerprint hashes the upload and the parameters.  A submission with a key:

1. :meth:`Idempotency.existing`: a job the key already names is the answer (200) when the fingerprint
   matches, ``409 idempotency_conflict`` when it does not;
2. :meth:`Idempotency.claim`, once the upload is parsed: takes the key for the job id about to be
   created, marked pending.  Naming the job before it exists means an API killed between creating the
   job and answering leaves a key that a retry resolves to that job, not a second one.  A key another
   request holds is answered with that request's job once it exists (up to :data:`IDEMPOTENCY_WAIT`
   seconds), else ``409 conflict`` + ``Retry-After``;
3. :meth:`Idempotency.confirm` after the job is created, :meth:`Idempotency.release` when creating failed.

A pending claim expires after ``fastmesh_jobs.idempotency.PENDING_TTL`` seconds, so one whose API process died
before creating the job does not block the key.  Without a key every step does nothing.
"""

from __future__ import annotations

import hashlib
import json
import time

from fastmesh_jobs.store import Store

from .errors import ApiError

IDEMPOTENCY_WAIT = 5.0  # seconds a retry waits for the job of a request holding the same Idempotency-Key


class Idempotency:
    """One submission's ``Idempotency-Key`` (or none) for ``who``, and what it is a key to."""

    def __init__(self, store: Store, who: str, key: str | None, data: bytes, params: dict,
                 conflict: str = "this Idempotency-Key was used for a different file or parameters"):
        """``conflict`` is the message of the 409 when the key names another request."""
        self.store, self.who, self.key, self.conflict = store, who, key or None, conflict
        self.fingerprint = "" if self.key is None else \
            hashlib.sha256(data + json.dumps(params, sort_keys=True).encode()).hexdigest()[:32]
        self._claim: str | None = None

    def existing(self, wait: float = 0.0) -> dict | None:
        """The job the key already names (same request), None if it names none; 409 for another request.

        A claim still pending whose job does not exist yet belongs to a request in flight (or to an API
        process killed before creating the job, whose claim expires); this waits up to ``wait`` seconds
        for its job to appear.
        """
        if self.key is None:
            return None
        deadline = time.monotonic() + wait
        while True:
            raw = self.store.idempotency_get(self.who, self.key)
            if raw is None:
                return None
            job_id, fp, *pending = raw.split(" ")
            job = self.store.get(job_id)
            mine = job is not None and job["owner"] == self.who
            if not mine and not pending:
                self.release()  # its job was deleted or expired: the key is free again
                return None
            if fp != self.fingerprint:
                raise ApiError(409, "idempotency_conflict", self.conflict)
            if mine:
                return job
            if time.monotonic() >= deadline:
                return None
            time.sleep(0.05)

    def claim(self, job_id: str) -> dict | None:
        """Take the key for ``job_id`` before creating it.  Returns the job of the request that holds the key
        instead (the answer to give), None once the key is ours; 409 while the other request is unfinished."""
        if self.key is None:
            return None
        self._claim = f"{job_id} {self.fingerprint} pending"
        if self.store.idempotency_claim(self.who, self.key, self._claim) is None:
            return None
        existing = self.existing(wait=IDEMPOTENCY_WAIT)
        if existing is not None:
            return existing
        # No job appeared: the holder's claim expired meanwhile (its API process died) and is ours to take.
        if self.store.idempotency_claim(self.who, self.key, self._claim) is not None:
            raise ApiError(409, "conflict", "a request with this Idempotency-Key is still being processed",
                           {"Retry-After": "1"})
        return None

    def confirm(self, job_id: str) -> None:
        """The job exists: the key names it for the job's retention."""
        if self.key is not None:
            self.store.idempotency_replace(self.who, self.key, self._claim, f"{job_id} {self.fingerprint}")

    def release(self) -> None:
        if self.key is not None:
            self.store.idempotency_release(self.who, self.key)
