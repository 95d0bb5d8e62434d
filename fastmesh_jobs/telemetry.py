"""What the job system counts for ``/metrics`` (``service.telemetry``): jobs by outcome and histograms of succeeded
jobs' stage durations and result-to-input distances.

Keys (``P`` is ``Settings.redis_prefix``)::

    P:stats:jobs            hash: submitted succeeded failed cancelled retried
    P:stats:stage:<stage>   hash: count sum b:<le> (a histogram of stage durations)
    P:stats:distance:<cd|hd>  hash: count sum b:<le> (a histogram of result-to-input distances)
"""

from __future__ import annotations

from .part import StorePart

STAGE_BUCKETS = (0.01, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0, 60.0, 120.0, 300.0, 600.0)
# Result-to-input distance (% of the input's size): validation meshes sit at CD 2-5, HD 8-25.
DISTANCE_BUCKETS = (0.5, 1.0, 2.0, 3.0, 4.0, 5.0, 7.5, 10.0, 15.0, 20.0, 30.0, 50.0)


class Telemetry(StorePart):
    """Job counters and histograms: written in the same pipeline as the change they count where there is one."""

    @property
    def k_job_counters(self) -> str:
        return f"{self.prefix}:stats:jobs"

    def count_job(self, event: str, pipe=None) -> None:
        """One more job ``event`` (submitted, succeeded, failed, cancelled, retried), on ``pipe`` if given."""
        (pipe if pipe is not None else self.redis).hincrby(self.k_job_counters, event, 1)

    def observe_success(self, pipe, timings: dict, result: dict | None) -> None:
        """Add a succeeded job's stage durations (``timings``, seconds) and its result's distances to the input
        (``result["quality"]``: ``cd``, ``hd``) to their histograms, on ``pipe``."""
        for k, v in timings.items():
            if v is not None:
                self._observe(pipe, f"stage:{k}", v, STAGE_BUCKETS)
        quality = (result or {}).get("quality") or {}
        for k in ("cd", "hd"):
            if quality.get(k) is not None:
                self._observe(pipe, f"distance:{k}", quality[k], DISTANCE_BUCKETS)

    def _observe(self, pipe, name: str, value: float, buckets: tuple[float, ...]) -> None:
        key = f"{self.prefix}:stats:{name}"
        pipe.hincrby(key, "count", 1)
        pipe.hincrbyfloat(key, "sum", float(value))
        for le in buckets:
            if value <= le:
                pipe.hincrby(key, f"b:{le}", 1)

    def stage_stats(self) -> dict[str, dict[str, float]]:
        """Per stage of succeeded jobs: count, sum and b:<le> of its duration in seconds."""
        return self._histograms("stage")

    def distance_stats(self) -> dict[str, dict[str, float]]:
        """Per distance (cd, hd) of succeeded jobs' results to their inputs: count, sum and b:<le>."""
        return self._histograms("distance")

    def _histograms(self, kind: str) -> dict[str, dict[str, float]]:
        out = {}
        for key in self.redis.scan_iter(f"{self.prefix}:stats:{kind}:*"):
            name = key.decode().rsplit(":", 1)[1]
            out[name] = {k.decode(): float(v) for k, v in self.redis.hgetall(key).items()}
        return out

    def job_counters(self) -> dict[str, int]:
        return {k.decode(): int(v) for k, v in self.redis.hgetall(self.k_job_counters).items()}
