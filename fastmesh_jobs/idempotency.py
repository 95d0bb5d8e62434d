"""The Redis side of ``Idempotency-Key``: which job a key names, claimed before the job exists.

Key (``P`` is ``Settings.redis_prefix``)::

    P:idem:<owner>:<sha>    "<job id> <request fingerprint>" for Idempotency-Key (+ " pending" until created)

The protocol that uses these steps is ``service.idempotency``.
"""

from __future__ import annotations

import hashlib

import redis

from .part import StorePart

PENDING_TTL = 10  # seconds an Idempotency-Key stays claimed by a request that has not created its job yet


class IdempotencyKeys(StorePart):
    """Get, claim, swap and release an owner's ``Idempotency-Key``."""

    def _k_idem(self, owner: str, key: str) -> str:
        return f"{self.prefix}:idem:{owner}:{hashlib.sha256(key.encode()).hexdigest()}"

    def idempotency_get(self, owner: str, key: str) -> str | None:
        """What ``key`` names: "<job id> <fingerprint>" or, while being created, "<job id> <fingerprint> pending"."""
        raw = self.redis.get(self._k_idem(owner, key))
        return raw.decode() if raw is not None else None

    def idempotency_claim(self, owner: str, key: str, job_id_fp: str) -> str | None:
        """Claim ``key`` for ``job_id_fp`` ("<job id> <fingerprint> pending").  Returns the existing claim, or
        None if ours.

        The claim lives ``PENDING_TTL`` seconds until :meth:`idempotency_replace` names the job: an API
        killed in between must not block the key for the whole retention time.
        """
        k = self._k_idem(owner, key)
        if self.redis.set(k, job_id_fp, nx=True, ex=PENDING_TTL):
            return None
        old = self.redis.get(k)
        return old.decode() if old else None

    def idempotency_replace(self, owner: str, key: str, old: str, new: str) -> bool:
        """Swap claim ``old`` for ``new`` (compare-and-set)."""
        k = self._k_idem(owner, key)
        with self.redis.pipeline() as pipe:
            try:
                pipe.watch(k)
                cur = pipe.get(k)
                if cur is not None and cur.decode() != old:
                    return False
                pipe.multi()
                pipe.set(k, new, ex=self.settings.retention_seconds)
                pipe.execute()
                return True
            except redis.WatchError:
                return False

    def idempotency_release(self, owner: str, key: str) -> None:
        self.redis.delete(self._k_idem(owner, key))
