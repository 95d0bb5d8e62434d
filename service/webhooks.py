"""Webhooks: a job submitted with ``callback_url`` is POSTed there, signed, when it succeeds, fails or is cancelled.

The job's final transition queues the delivery in Redis (``P:webhooks``, job id -> when due) in the same
step as the status change (:meth:`fastmesh_jobs.store.Store.finish`), so no delivery is lost with a process.
A dispatcher thread in each API process (:func:`dispatch_loop`) claims due entries and delivers them from a
few threads of its own: workers never wait on a receiver.  A claim is a lease: a dispatcher that dies
mid-delivery leaves the entry due again :data:`LEASE_SECONDS` later, so delivery is at least once.

The body is the job JSON as ``GET /v1/jobs/{id}`` shows it, signed ``X-FastMesh-Signature:
sha256=<hex HMAC-SHA256 of the raw body>`` with ``webhook_secret``.  A delivery answered 2xx is done;
anything else (another status, a timeout, a refused address) is retried after ``webhook_backoff_seconds``,
doubling, up to ``webhook_max_attempts``; the job's ``webhook`` field shows the attempts and the last outcome.

Addresses (SSRF): a callback goes to https and public addresses only, unless ``webhook_allow_private``.
Its host is resolved and every address checked at submission, and again at each delivery, which then
connects to the address it checked (the name's TLS certificate still verified), so a name that resolves
elsewhere later (DNS rebinding) cannot point a delivery at the service's own network.
"""

from __future__ import annotations

import hashlib
import hmac
import ipaddress
import json
import logging
import socket
import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from concurrent.futures import TimeoutError as FutureTimeout
from urllib.parse import urlsplit

import httpcore
import httpx

from fastmesh_jobs.settings import Settings
from fastmesh_jobs.states import FINAL, iso
from fastmesh_jobs.store import Store

log = logging.getLogger("fastmesh.webhooks")

MAX_URL_LENGTH = 2000
RESOLVE_SECONDS = 5.0  # longest wait for DNS at submission; a slower name is refused
DISPATCH_INTERVAL = 0.25  # seconds between two looks for due deliveries
DELIVERY_THREADS = 4  # deliveries under way at once per API process
LEASE_SECONDS = 120  # a claimed delivery whose dispatcher died is due again after this long
SIGNATURE_HEADER = "X-FastMesh-Signature"

# KEYS: webhooks zset.  ARGV: job id, now, lease end.  Claim a due entry: push its due time past the lease.
_CLAIM = """
local due = redis.call('ZSCORE', KEYS[1], ARGV[1])
if not due or tonumber(due) > tonumber(ARGV[2]) then return 0 end
redis.call('ZADD', KEYS[1], ARGV[3], ARGV[1])
return 1
"""

Resolver = Callable[[str, int], list[str]]


class UnsafeUrl(ValueError):
    """A callback URL that may not be called: its message says why."""


def resolve(host: str, port: int) -> list[str]:
    """Every address ``host`` resolves to (IPv4 and IPv6)."""
    infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    return list(dict.fromkeys(info[4][0] for info in infos))


def is_public(address: str) -> bool:
    """Whether ``address`` is a globally routable unicast address (an IPv4-mapped IPv6 one is judged as its IPv4)."""
    ip = ipaddress.ip_address(address.split("%", 1)[0])
    if isinstance(ip, ipaddress.IPv6Address) and ip.ipv4_mapped is not None:
        ip = ip.ipv4_mapped
    return ip.is_global and not ip.is_multicast


def vet(url: str, allow_private: bool, resolver: Resolver = resolve) -> tuple[str, int, str]:
    """Check a callback URL and resolve its host.

    Returns
    -------
    (host, port, address)
        The host as written, the port, and the checked address to connect to.

    Raises
    ------
    UnsafeUrl
        The URL is malformed, not https (plain http only with ``allow_private``), carries credentials, or
        its host does not resolve or resolves to any non-public address (unless ``allow_private``).
    """
    if len(url) > MAX_URL_LENGTH:
        raise UnsafeUrl(f"longer than {MAX_URL_LENGTH} characters")
    try:
        parts = urlsplit(url)
        port = parts.port
    except ValueError as e:
        raise UnsafeUrl(f"not a URL ({e})") from None
    schemes = ("https", "http") if allow_private else ("https",)
    if parts.scheme not in schemes:
        raise UnsafeUrl("must be an https:// URL" + ("" if allow_private else
                                                     " (plain http needs FASTMESH_WEBHOOK_ALLOW_PRIVATE=1)"))
    if not parts.hostname:
        raise UnsafeUrl("has no host")
    if parts.username is not None or parts.password is not None:
        raise UnsafeUrl("must not carry credentials; the signature authenticates the service")
    port = port or (443 if parts.scheme == "https" else 80)
    try:
        addresses = resolver(parts.hostname, port)
    except (OSError, UnicodeError) as e:
        raise UnsafeUrl(f"host '{parts.hostname[:100]}' does not resolve ({e})") from None
    if not addresses:
        raise UnsafeUrl(f"host '{parts.hostname[:100]}' does not resolve")
    if not allow_private:
        bad = [a for a in addresses if not is_public(a)]
        if bad:
            raise UnsafeUrl(f"host '{parts.hostname[:100]}' resolves to the non-public address {bad[0]}; "
                            "callbacks go to public addresses only")
    return parts.hostname, port, addresses[0]


def vet_at_submit(url: str, allow_private: bool, resolver: Resolver = resolve) -> None:
    """:func:`vet` with a time limit on resolving (a name server that never answers must not hold a request)."""
    pool = ThreadPoolExecutor(max_workers=1)
    try:
        pool.submit(vet, url, allow_private, resolver).result(timeout=RESOLVE_SECONDS)
    except FutureTimeout:
        raise UnsafeUrl(f"its host did not resolve within {RESOLVE_SECONDS:g} s") from None
    finally:
        pool.shutdown(wait=False)


def new_webhook(url: str) -> dict:
    """The ``webhook`` field of a new job (the job JSON's ``webhook``)."""
    return {"url": url, "state": "waiting", "attempts": 0, "last_status": None, "last_error": None,
            "last_attempt_at": None, "next_attempt_at": None}


def sign(secret: str, body: bytes) -> str:
    """The ``X-FastMesh-Signature`` value of ``body``."""
    return "sha256=" + hmac.new(secret.encode(), body, hashlib.sha256).hexdigest()


class _Deadline(httpcore.SyncBackend):
    """Sockets whose every wait is cut to what is left of one deadline: a receiver that answers a byte at a
    time cannot hold a delivery thread past ``webhook_timeout_seconds`` (a per-read timeout alone would let it)."""

    def __init__(self, seconds: float):
        super().__init__()
        self.end = time.monotonic() + seconds

    def left(self, timeout: float | None) -> float:
        left = self.end - time.monotonic()
        if left <= 0:
            raise httpcore.ReadTimeout("no complete answer within webhook_timeout_seconds")
        return left if timeout is None else min(timeout, left)

    def connect_tcp(self, host, port, timeout=None, local_address=None, socket_options=None):
        return _DeadlineStream(super().connect_tcp(host, port, self.left(timeout), local_address, socket_options),
                               self)


class _DeadlineStream(httpcore.NetworkStream):
    def __init__(self, inner: httpcore.NetworkStream, deadline: _Deadline):
        self.inner, self.deadline = inner, deadline

    def read(self, max_bytes: int, timeout: float | None = None) -> bytes:
        return self.inner.read(max_bytes, self.deadline.left(timeout))

    def write(self, buffer: bytes, timeout: float | None = None) -> None:
        self.inner.write(buffer, self.deadline.left(timeout))

    def close(self) -> None:
        self.inner.close()

    def start_tls(self, ssl_context, server_hostname=None, timeout=None) -> httpcore.NetworkStream:
        return _DeadlineStream(self.inner.start_tls(ssl_context, server_hostname, self.deadline.left(timeout)),
                               self.deadline)

    def get_extra_info(self, info: str):
        return self.inner.get_extra_info(info)


def post(url: str, body: bytes, headers: dict, settings: Settings, resolver: Resolver = resolve) -> int:
    """POST ``body`` to ``url`` at the address :func:`vet` checks now; the response's status.

    The connection goes to that address with the URL's host in ``Host`` and in TLS (SNI and certificate
    check), so what is called is what was checked.  Redirects are not followed, no proxy is used, the response
    body is not read, and the whole exchange has ``webhook_timeout_seconds``.

    Raises
    ------
    UnsafeUrl, httpcore.TimeoutException, httpcore.NetworkError, httpcore.ProtocolError
    """
    host, port, address = vet(url, settings.webhook_allow_private, resolver)
    parts = urlsplit(url)
    literal = f"[{address}]" if ":" in address else address
    target = parts._replace(netloc=f"{literal}:{port}").geturl()
    t = settings.webhook_timeout_seconds
    # httpcore, the layer under httpx: its connection pool takes the network backend that keeps the deadline.
    with httpcore.ConnectionPool(ssl_context=httpx.create_ssl_context(), network_backend=_Deadline(t)) as pool:
        with pool.stream("POST", target, content=body, headers={**headers, "Host": parts.netloc},
                         extensions={"sni_hostname": host,
                                     "timeout": {"connect": t, "read": t, "write": t, "pool": t}}) as response:
            return response.status  # the body is never read: a receiver cannot make it large


def attempt(store: Store, job_id: str, resolver: Resolver = resolve) -> str:
    """One delivery of ``job_id``'s webhook and its bookkeeping; what became of it: "delivered", "retry",
    "failed" or "dropped" (the job is gone, not final, or its webhook already settled)."""
    s = store.settings
    job = store.get(job_id)
    hook = (job or {}).get("webhook")
    if job is None or job["status"] not in FINAL or not hook or hook.get("state") not in ("waiting", "retrying"):
        store.redis.zrem(store.k_webhooks, job_id)
        return "dropped"
    body = json.dumps(store.public(job), separators=(",", ":")).encode()
    status, error = None, None
    if s.webhook_secret is None:
        error = "FASTMESH_WEBHOOK_SECRET is unset: nothing to sign with"
    else:
        headers = {"Content-Type": "application/json", "User-Agent": "FastMesh-Webhook",
                   SIGNATURE_HEADER: sign(s.webhook_secret.get_secret_value(), body),
                   "X-FastMesh-Event": f"job.{job['status']}", "X-FastMesh-Job": job_id}
        try:
            status = post(hook["url"], body, headers, s, resolver)
        except UnsafeUrl as e:
            error = f"refused: {e}"
        except Exception as e:  # any failure to deliver is this attempt's outcome, recorded on the job
            error = f"{type(e).__name__}: {str(e)[:200] or 'no detail'}"
    now = time.time()
    n = hook["attempts"] + 1
    ok = status is not None and 200 <= status < 300
    outcome = "delivered" if ok else "failed" if n >= s.webhook_max_attempts else "retry"
    due = now + s.webhook_backoff_seconds * 2 ** (n - 1)
    if error is None and not ok:
        error = f"the receiver answered {status}"
    hook = {**hook, "attempts": n, "last_status": status, "last_error": error, "last_attempt_at": iso(now),
            "state": {"retry": "retrying"}.get(outcome, outcome),
            "next_attempt_at": iso(due) if outcome == "retry" else None}
    store.transition(job_id, FINAL, {"webhook": hook})  # never recreates a job deleted meanwhile
    if outcome == "retry":
        store.redis.zadd(store.k_webhooks, {job_id: due})
    else:
        store.redis.zrem(store.k_webhooks, job_id)
    return outcome


def dispatch_once(store: Store, pool: ThreadPoolExecutor, busy: set[str], lock: threading.Lock,
                  resolver: Resolver = resolve) -> int:
    """Claim due deliveries (as many as there are free threads) and start them in ``pool``; how many."""
    free = DELIVERY_THREADS - len(busy)
    if free <= 0:
        return 0
    now = time.time()
    started = 0
    for raw in store.redis.zrangebyscore(store.k_webhooks, "-inf", now, start=0, num=free):
        job_id = raw.decode()
        if job_id in busy or not store.redis.eval(_CLAIM, 1, store.k_webhooks, job_id, now, now + LEASE_SECONDS):
            continue
        with lock:
            busy.add(job_id)

        def run(job_id=job_id):
            try:
                outcome = attempt(store, job_id, resolver)
                log.info("webhook of job %s: %s", job_id, outcome)
            except Exception as e:  # Redis down: the lease brings the entry back
                log.warning("webhook of job %s: %s", job_id, e)
            finally:
                with lock:
                    busy.discard(job_id)
        pool.submit(run)
        started += 1
    return started


def dispatch_loop(store: Store, stop: threading.Event, resolver: Resolver = resolve) -> None:
    """Deliver due webhooks every :data:`DISPATCH_INTERVAL` seconds until ``stop`` is set."""
    busy: set[str] = set()
    lock = threading.Lock()
    with ThreadPoolExecutor(max_workers=DELIVERY_THREADS, thread_name_prefix="fastmesh-webhook") as pool:
        while not stop.wait(DISPATCH_INTERVAL):
            try:
                dispatch_once(store, pool, busy, lock, resolver)
            except Exception as e:  # Redis down: try again next tick
                log.warning("webhook dispatcher: %s", e)
