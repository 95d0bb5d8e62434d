"""Webhooks: a job submitted with ``callback_url`` is POSTed there, signed, when it succeeds, fails or is cancelled.

The job's final transition queues the delivery in Redis (``P:webhooks``, job id -> when due) in the same
step as the status change (:meth:`fastmesh_jobs.store.Store.finish`), so no delivery is lost with a process.
A dispatcher thread in each API process (:func:`dispatch_loop`) claims due entries and delivers them from
threads of its own, fairly between API keys (:class:`Dispatcher`): workers never wait on a receiver, and one
key's hanging receivers do not hold up another key's deliveries.  A claim is a lease: a dispatcher that dies
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
from collections import Counter
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
DELIVERY_THREADS = 16  # deliveries under way at once per API process
DELIVERIES_PER_KEY = 4  # of which one API key's: what a key whose receivers all hang can hold
SCAN = 200  # due entries looked at per dispatch
DEFER_SECONDS = 1.0  # how long a due entry of a key at its limit is put off when more are due than looked at
LEASE_SECONDS = 120  # a claimed delivery whose dispatcher died is due again after this long
SIGNATURE_HEADER = "X-FastMesh-Signature"

# KEYS: webhooks zset.  ARGV: job id, now, new due time.  Push a due entry to the new time, if it is still due:
# a claim (past the lease) or, for a key at its limit, a deferral (Dispatcher.tick).
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


# IPv6 addresses that stand for the IPv4 address in their low 32 bits (a NAT64 gateway, RFC 6052's well-known
# prefix, or a SIIT translator, RFC 2765, delivers there): as public as that IPv4 address.
_TRANSLATED = tuple(ipaddress.ip_network(n) for n in ("64:ff9b::/96", "::ffff:0:0:0/96"))
# IPv6 ranges never called, whatever they hold: IPv4-compatible addresses (deprecated, RFC 4291), local-use NAT64
# (RFC 8215: its IPv4 address lies where the operator chose), the 6to4 (deprecated, RFC 7526) and Teredo tunnels
# (to the IPv4 address they hold), site-local (deprecated, RFC 3879).
_NEVER_PUBLIC = tuple(ipaddress.ip_network(n) for n in ("::/96", "64:ff9b:1::/48", "2002::/16", "2001::/32",
                                                         "fec0::/10"))


def is_public(address: str) -> bool:
    """Whether ``address`` is a globally routable unicast address.  An IPv6 address that carries an IPv4 one
    (IPv4-mapped, NAT64, SIIT) is judged by that IPv4 address; the other forms that carry one are refused
    (:data:`_NEVER_PUBLIC`)."""
    ip = ipaddress.ip_address(address.split("%", 1)[0])
    if isinstance(ip, ipaddress.IPv6Address):
        if any(ip in net for net in _NEVER_PUBLIC):
            return False
        if ip.ipv4_mapped is not None:
            return is_public(str(ip.ipv4_mapped))
        if any(ip in net for net in _TRANSLATED):
            return is_public(str(ipaddress.IPv4Address(int(ip) & 0xFFFFFFFF)))
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
        The URL holds a character outside printable ASCII (a space, CR, LF), is malformed, not https (plain
        http only with ``allow_private``), carries credentials, or its host does not resolve or resolves to any
        non-public address (:func:`is_public`; unless ``allow_private``).
    """
    if len(url) > MAX_URL_LENGTH:
        raise UnsafeUrl(f"longer than {MAX_URL_LENGTH} characters")
    bad = next((i for i, c in enumerate(url) if not "!" <= c <= "~"), None)
    if bad is not None:  # HTTP cannot send it in a request line or Host; Python's urlsplit drops CR, LF, tab
        raise UnsafeUrl(f"character {bad + 1} is {url[bad]!r}: a URL holds printable ASCII only (no spaces, "
                        "CR, LF or other control characters); percent-encode it")
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


def fair_order(due: list[tuple[str, str]], under_way: Counter) -> list[tuple[int, str, str]]:
    """``(rank, job id, owner)`` of the ``due`` deliveries (``(job id, owner)``, earliest due first), taken
    round-robin between owners: an entry's rank is how many of its owner's deliveries would be under way before
    it (``under_way[owner]`` plus its place among the owner's due entries); lowest rank first, then due time."""
    seen: Counter = Counter()
    ranked = []
    for place, (job_id, owner) in enumerate(due):
        ranked.append((under_way[owner] + seen[owner], place, job_id, owner))
        seen[owner] += 1
    return [(rank, job_id, owner) for rank, _, job_id, owner in sorted(ranked)]


class Dispatcher:
    """Starts due deliveries in a pool of :data:`DELIVERY_THREADS` threads, fairly between API keys.

    A key has at most :data:`DELIVERIES_PER_KEY` deliveries under way, and keys take turns
    (:func:`fair_order`): a key whose receivers hang until the timeout holds that many threads, never the
    others' turns.  The due entries are looked at :data:`SCAN` at a time; when that many are due, those of keys
    at their limit are put off :data:`DEFER_SECONDS`, so the entries of other keys behind them come up.
    """

    def __init__(self, store: Store, pool: ThreadPoolExecutor, resolver: Resolver = resolve,
                 done: threading.Event | None = None):
        """``done`` is set whenever a delivery ends (a thread is free again)."""
        self.store, self.pool, self.resolver = store, pool, resolver
        self.done = done or threading.Event()
        self.lock = threading.Lock()
        self.busy: dict[str, str] = {}  # job id -> owner: the deliveries under way

    def due(self, now: float) -> tuple[list[tuple[str, str]], bool]:
        """``([(job id, owner)], more)``: up to :data:`SCAN` due entries not under way, earliest first (owner ""
        for a job that is gone), and whether the look was cut at :data:`SCAN`."""
        store = self.store
        ids = [raw.decode() for raw in store.redis.zrangebyscore(store.k_webhooks, "-inf", now, start=0, num=SCAN)]
        with store.redis.pipeline(transaction=False) as pipe:
            for job_id in ids:
                pipe.hget(store.k_job(job_id), "owner")
            owners = pipe.execute()
        with self.lock:
            due = [(j, (o or b"").decode()) for j, o in zip(ids, owners, strict=True) if j not in self.busy]
        return due, len(ids) == SCAN

    def tick(self) -> int:
        """Claim due deliveries for the free threads and start them; how many were started."""
        with self.lock:
            free = DELIVERY_THREADS - len(self.busy)
            under_way = Counter(self.busy.values())
        if free <= 0:
            return 0
        now = time.time()
        due, more = self.due(now)
        started = 0
        for rank, job_id, owner in fair_order(due, under_way):
            if rank >= DELIVERIES_PER_KEY or started >= free:
                if more and rank >= DELIVERIES_PER_KEY:  # out of the way of the entries past the look
                    self.store.redis.eval(_CLAIM, 1, self.store.k_webhooks, job_id, now, now + DEFER_SECONDS)
                continue
            if self.store.redis.eval(_CLAIM, 1, self.store.k_webhooks, job_id, now, now + LEASE_SECONDS):
                self.start(job_id, owner)
                started += 1
        return started

    def start(self, job_id: str, owner: str) -> None:
        """Deliver the claimed ``job_id`` in the pool."""
        with self.lock:
            self.busy[job_id] = owner

        def run():
            try:
                outcome = attempt(self.store, job_id, self.resolver)
                log.info("webhook of job %s: %s", job_id, outcome)
            except Exception as e:  # Redis down: the lease brings the entry back
                log.warning("webhook of job %s: %s", job_id, e)
            finally:
                with self.lock:
                    self.busy.pop(job_id, None)
                self.done.set()
        self.pool.submit(run)


def dispatch_loop(store: Store, stop: threading.Event, resolver: Resolver = resolve) -> None:
    """Deliver due webhooks until ``stop`` is set: a look every :data:`DISPATCH_INTERVAL` seconds, and at once
    when a delivery ends (a key's next delivery need not wait for the tick)."""
    done = threading.Event()
    with ThreadPoolExecutor(max_workers=DELIVERY_THREADS, thread_name_prefix="fastmesh-webhook") as pool:
        dispatcher = Dispatcher(store, pool, resolver, done)
        while not stop.is_set():
            done.wait(DISPATCH_INTERVAL)
            done.clear()
            if stop.is_set():
                break
            try:
                dispatcher.tick()
            except Exception as e:  # Redis down: try again next tick
                log.warning("webhook dispatcher: %s", e)
