"""Prometheus metrics of the API process plus the job state the workers leave in Redis.

Requests are counted in-process.  Jobs by status, queue depth, live workers and stage durations
are read from Redis at scrape time (workers run elsewhere and write their observations there),
so one scrape of any API process shows the whole service.
"""

from __future__ import annotations

import logging

from prometheus_client import CollectorRegistry, Counter, Histogram, disable_created_metrics, generate_latest
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, HistogramMetricFamily

from fastmesh_jobs.store import Store
from fastmesh_jobs.telemetry import DISTANCE_BUCKETS, STAGE_BUCKETS

log = logging.getLogger("fastmesh.service")
disable_created_metrics()  # the *_created series only add noise to every scrape


class _RedisCollector:
    def __init__(self, store: Store):
        self.store = store

    def collect(self):
        try:
            counters = self.store.job_counters()
            depth = self.store.queue_depth()
            running = self.store.running_count()
            workers = len(self.store.workers_alive())
            stages = self.store.stage_stats()
            distances = self.store.distance_stats()
        except Exception as e:  # a scrape must not fail because Redis blinked; report it instead
            log.warning("metrics: redis unreachable: %s", e)
            up = GaugeMetricFamily("fastmesh_redis_up", "1 when Redis answered this scrape")
            up.add_metric([], 0)
            yield up
            return
        up = GaugeMetricFamily("fastmesh_redis_up", "1 when Redis answered this scrape")
        up.add_metric([], 1)
        yield up
        c = CounterMetricFamily("fastmesh_jobs", "Jobs that reached a status (submitted, succeeded, failed, "
                                                 "cancelled, retried)", labels=["status"])
        for status in ("submitted", "succeeded", "failed", "cancelled", "retried"):
            c.add_metric([status], counters.get(status, 0))
        yield c
        g = GaugeMetricFamily("fastmesh_jobs_current", "Jobs now in a non-final status", labels=["status"])
        g.add_metric(["queued"], depth)
        g.add_metric(["running"], running)
        yield g
        q = GaugeMetricFamily("fastmesh_queue_depth", "Jobs waiting in the queue")
        q.add_metric([], depth)
        yield q
        w = GaugeMetricFamily("fastmesh_workers_alive", "Workers with a recent heartbeat")
        w.add_metric([], workers)
        yield w
        yield _histogram("fastmesh_stage_seconds", "Duration of each stage of succeeded jobs", "stage", stages,
                         STAGE_BUCKETS)
        yield _histogram("fastmesh_result_distance_percent", "Distance of each succeeded job's result to its input "
                         "(Chamfer cd, Hausdorff hd) in % of the input's size", "metric", distances,
                         DISTANCE_BUCKETS)


def _histogram(name: str, doc: str, label: str, stats: dict[str, dict[str, float]],
               bounds: tuple[float, ...]) -> HistogramMetricFamily:
    """A histogram family from the count/sum/b:<le> hashes that ``Store.finish`` keeps in Redis."""
    h = HistogramMetricFamily(name, doc, labels=[label])
    for value, s in sorted(stats.items()):
        buckets = [(str(le), s.get(f"b:{le}", 0.0)) for le in bounds]
        buckets.append(("+Inf", s.get("count", 0.0)))
        h.add_metric([value], buckets, s.get("sum", 0.0))
    return h


class Metrics:
    """One registry per app (so tests can build several apps in one process)."""

    def __init__(self, store: Store):
        self.registry = CollectorRegistry()
        self.requests = Counter("fastmesh_http_requests", "HTTP requests", ["method", "route", "status"],
                                registry=self.registry)
        self.latency = Histogram("fastmesh_http_request_seconds", "HTTP request latency", ["method", "route"],
                                 buckets=(0.001, 0.0025, 0.005, 0.01, 0.02, 0.05, 0.1, 0.25, 0.5, 1, 2.5, 10),
                                 registry=self.registry)
        self.registry.register(_RedisCollector(store))

    def observe_request(self, method: str, route: str, status: int, seconds: float) -> None:
        self.requests.labels(method, route, str(status)).inc()
        self.latency.labels(method, route).observe(seconds)

    def render(self) -> bytes:
        return generate_latest(self.registry)
