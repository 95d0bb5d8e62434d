"""How much a key, an address or the queue may take: per-minute request windows, the authentication lockout, and
admission to the queue.

Keys (``P`` is ``Settings.redis_prefix``)::

    P:rate:<kind>:<owner>:<minute>   fixed-window request counters (kind ``authfail``: per address, not owner)
    P:authok:<address>:<owner>  a key that authenticated from an address before a lockout (:meth:`auth_admit`)
    P:queued                zset job id -> time enqueued, owned by ``states``; admission adds to it here
"""

from __future__ import annotations

import math
import time

from .part import StorePart

# KEYS: failed authentications of an address this minute, the (address, owner) pair's mark.  ARGV: limit, ttl.
_AUTH_ADMIT = """
local limit = tonumber(ARGV[1])
if limit <= 0 then return 1 end
if tonumber(redis.call('GET', KEYS[1]) or '0') < limit then
  redis.call('SET', KEYS[2], '1', 'EX', ARGV[2])
  return 1
end
return redis.call('EXISTS', KEYS[2])
"""
AUTH_REMEMBER_SECONDS = 3600  # a key that authenticated from an address is not locked out there for this long

# KEYS: queued zset.  ARGV: job id, now, limit.  Admission to the queue: check and add in one step, so
# concurrent submissions cannot all see room and overshoot the limit together.
_ADMIT = """
if redis.call('ZCARD', KEYS[1]) >= tonumber(ARGV[3]) then return 0 end
redis.call('ZADD', KEYS[1], ARGV[2], ARGV[1])
return 1
"""


class QueueFull(Exception):
    """``create`` found ``max_queued`` jobs already waiting."""


class Limits(StorePart):
    """Request windows per minute, the lockout of addresses that fail to authenticate, the queue's size limit."""

    def _k_rate(self, kind: str, owner: str, window: int) -> str:
        return f"{self.prefix}:rate:{kind}:{owner}:{window}"

    def rate_hit(self, kind: str, owner: str, limit: int) -> int:
        """Count one request in this minute's window; return seconds to wait (0 = allowed)."""
        if limit <= 0:
            return 0
        now = time.time()
        window = int(now // 60)
        k = self._k_rate(kind, owner, window)
        with self.redis.pipeline() as pipe:
            pipe.incr(k)
            pipe.expire(k, 61)
            count = pipe.execute()[0]
        return 0 if count <= limit else max(1, int(math.ceil((window + 1) * 60 - now)))

    def rate_wait(self, kind: str, owner: str, limit: int) -> int:
        """Seconds to wait when this minute's window already holds ``limit`` hits (0 = allowed); counts nothing."""
        if limit <= 0:
            return 0
        now = time.time()
        window = int(now // 60)
        count = int(self.redis.get(self._k_rate(kind, owner, window)) or 0)
        return 0 if count < limit else max(1, int(math.ceil((window + 1) * 60 - now)))

    def auth_admit(self, address: str, owner: str, limit: int, remember: int = AUTH_REMEMBER_SECONDS) -> bool:
        """Whether ``owner``'s key may pass from ``address``: while the address's failed authentications are
        under ``limit`` it may (and the pair is remembered for ``remember`` seconds); past it only a
        remembered pair may."""
        window = int(time.time() // 60)
        return bool(self.redis.eval(_AUTH_ADMIT, 2, self._k_rate("authfail", address, window),
                                    f"{self.prefix}:authok:{address}:{owner}", limit, remember))

    def admit(self, k_queued: str, job_id: str, now: float, max_queued: int) -> None:
        """Add ``job_id`` to the queued set ``k_queued`` at ``now`` if it holds fewer than ``max_queued`` jobs,
        in one step; else raise :class:`QueueFull`."""
        if not self._script(_ADMIT)(keys=[k_queued], args=[job_id, now, max_queued]):
            raise QueueFull(job_id)
