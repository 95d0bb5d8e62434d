"""Every knob of the service and its workers, read from ``FASTMESH_*`` environment variables.

One class for the API, the workers and ``make run``: a worker on another machine needs only
``FASTMESH_REDIS_URL`` (plus the same prefix and queue name if those were changed).
"""

from __future__ import annotations

from typing import Annotated

from pydantic import Field, SecretStr, field_validator
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict

from fastmesh.shapes.shape import EXPORT_FORMATS

CommaList = Annotated[list[str], NoDecode]


class Settings(BaseSettings):
    """Configuration; each field is the environment variable ``FASTMESH_<NAME>``."""

    model_config = SettingsConfigDict(env_prefix="FASTMESH_", extra="ignore")

    # --- where things live
    redis_url: str = Field("redis://127.0.0.1:6379/0", description="Redis holding jobs, inputs, results and the queue.")
    redis_prefix: str = Field("fastmesh", description="Prefix of every key the service writes (the RQ queue aside).")
    redis_maxmemory: str = Field("1gb", description="Memory cap of the redis-server `make run` starts (policy "
                                 "noeviction: when full, submissions get 503 and no queued job is evicted).")
    queue_name: str = Field("fastmesh", description="RQ queue the API fills and the workers drain.")
    host: str = Field("127.0.0.1", description="Address the API listens on.")
    port: int = Field(8000, description="Port the API listens on.")

    # --- access
    api_keys: CommaList = Field(default_factory=list,
                                description="Comma-separated bearer keys; empty = no authentication.")
    cors_origins: CommaList = Field(default_factory=list,
                                    description="Comma-separated origins allowed by CORS ('*' for any); empty = off.")
    rate_limit_per_minute: int = Field(1200, ge=0, description="/v1 requests per key (or IP) per minute; 0 = off.")
    auth_fail_limit_per_minute: int = Field(30, ge=0, description="Failed authentications per client address per "
                                            "minute; past it requests from there get 429, except those with a key "
                                            "that authenticated from there before the limit was reached; 0 = off.")
    trusted_proxies: CommaList = Field(default_factory=list,
                                       description="Comma-separated addresses of reverse proxies whose "
                                       "`X-Forwarded-For` names the client; empty = the header is ignored.")
    submit_rate_limit_per_minute: int = Field(120, ge=0, description="Job submissions per key per minute; 0 = off.")

    # --- input limits
    max_upload_bytes: int = Field(64 * 1024 * 1024, gt=0, description="Largest accepted upload (413 above).")
    max_points: int = Field(500_000, gt=0, description="Most points / vertices in an input.")
    max_faces: int = Field(1_000_000, gt=0, description="Most faces in an input mesh.")
    max_queue_depth: int = Field(100, ge=1, description="Queued jobs above which submissions get 429.")
    default_formats: CommaList = Field(default_factory=lambda: ["glb"],
                                       description="Formats exported by the worker when a job names none.")
    body_timeout_seconds: float = Field(30.0, gt=0, description="A request body with no bytes arriving for this "
                                        "long is answered 408 (slow or stalled clients).")
    header_timeout_seconds: float = Field(10.0, gt=0, description="A request line and headers not complete this "
                                          "long after their first byte are answered 408 (with "
                                          "`--http service.http:Protocol`, as `make run` and the image serve).")
    max_concurrent_parses: int = Field(3, ge=1, description="Uploads read and parsed at once by one API process, "
                                       "one key at most all but one; further ones wait up to parse_wait_seconds, "
                                       "then get 429 (busy).")
    parse_wait_seconds: float = Field(1.0, ge=0, description="Longest wait of an upload for a parsing slot.")
    upload_deadline_seconds: float = Field(300.0, gt=0, description="A request body not complete this long after "
                                           "the request began is answered 408, however steadily it trickles.")
    child_memory_mb: int = Field(1536, ge=384, description="Address-space cap in MiB of each child process that "
                                 "parses an upload, samples an input or renders a preview (its libraries take about "
                                 "330); what needs more is refused (413) and the API process never grows with a file.")
    parse_timeout_seconds: float = Field(60.0, gt=0, description="An upload not parsed in this time is refused "
                                         "(413) and its child process killed.")
    max_wait_seconds: float = Field(300.0, ge=0, description="Longest long-poll of GET .../result?wait=S.")

    max_batch_files: int = Field(16, ge=1, le=100, description="Most files in one POST /v1/batches.")

    # --- jobs and workers
    retention_seconds: int = Field(24 * 3600, gt=0, description="How long a job, its input and its results stay "
                                   "in Redis after it finishes (the job's `expires_at`).")
    job_timeout: float = Field(600.0, gt=0, description="Seconds a job may run before it fails with 'timeout'.")
    max_attempts: int = Field(3, ge=1, description="Runs of a job whose worker died before it fails 'worker_lost'.")
    heartbeat_interval: float = Field(2.0, gt=0, description="Seconds between a worker's heartbeats.")
    heartbeat_ttl: float = Field(10.0, gt=0, description="A running job whose heartbeat is older is taken as lost.")
    reaper_interval: float = Field(3.0, gt=0, description="Seconds between scans for lost and overdue jobs.")
    progress_interval: float = Field(0.25, ge=0, description="Least seconds between two progress writes of a job.")
    redis_outage_wait: float = Field(60.0, gt=0, description="Seconds a worker whose Redis vanished mid-job waits for "
                                     "it before giving up (the job is then requeued by the reaper).")
    weights: str | None = Field(None, description="Weights directory for the workers; unset = shipped weights.")
    device: str | None = Field(None, description="Torch device for the workers (cpu, cuda); unset = best available.")
    debug_step_delay: float = Field(0.0, ge=0, description="Testing only: a worker sleeps this long in every "
                                    "progress callback, so fault and cancellation tests can catch a job mid-run.")
    max_batch: int | None = Field(None, ge=1, le=64, description="Jobs one worker runs at once, their vertex "
                                  "decoding batched (a queued job joins when one ends); unset = 1 on a CPU (where "
                                  "batching measured no faster than one job at a time), 8 on a GPU.")
    torch_threads: int | None = Field(None, ge=1, description="torch threads in a worker; unset = the pipeline's "
                                     "choice (1 on CPU, the fastest measured for one job at a time).")

    # --- webhooks (service.webhooks)
    webhook_secret: SecretStr | None = Field(None, description="Key of the HMAC-SHA256 signature of webhook bodies "
                                             "(`X-FastMesh-Signature`); unset = `callback_url` is refused.")
    webhook_allow_private: bool = Field(False, description="Allow callback URLs over plain http and to private, "
                                        "loopback, link-local and other non-public addresses (tests, closed "
                                        "networks); off = https to public addresses only.")
    webhook_max_attempts: int = Field(8, ge=1, le=50, description="Deliveries tried per job before the webhook "
                                      "is given up (`webhook.state` failed).")
    webhook_backoff_seconds: float = Field(5.0, gt=0, description="Wait before the first retry of a webhook; "
                                           "it doubles with each further attempt.")
    webhook_timeout_seconds: float = Field(10.0, gt=0, description="Longest wait for a receiver to answer one "
                                           "delivery.")

    @field_validator("api_keys", "cors_origins", "default_formats", "trusted_proxies", mode="before")
    @classmethod
    def _split_commas(cls, v):
        if isinstance(v, str):
            return [s.strip() for s in v.split(",") if s.strip()]
        return v

    @field_validator("default_formats")
    @classmethod
    def _known_formats(cls, v: list[str]) -> list[str]:
        v = [f.lower() for f in v]
        bad = [f for f in v if f not in EXPORT_FORMATS]
        if bad or not v:
            raise ValueError(f"default_formats must be a non-empty subset of {', '.join(EXPORT_FORMATS)}")
        return v


def settings_table() -> str:
    """README's settings table: one row per field of :class:`Settings`, its variable, default and description
    (a test keeps README equal to it)."""

    def default(field) -> str:
        value = field.get_default(call_default_factory=True)
        if value is None or value == []:
            return "unset"
        if isinstance(value, list):
            value = ",".join(value)
        return f"`{value}`"

    rows = ["| variable | default | what |", "|---|---|---|"]
    for name, field in Settings.model_fields.items():
        what = (field.description or "").replace("|", "\\|")
        rows.append(f"| `FASTMESH_{name.upper()}` | {default(field)} | {what} |")
    return "\n".join(rows)
