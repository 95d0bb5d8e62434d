"""Webhooks (service.webhooks): callback_url is checked at submission (https, public addresses), the finished
job is POSTed to a local receiver, signed, and retried with backoff; the job shows the attempts.

The receiver is a small HTTP server on 127.0.0.1: the apps here set webhook_allow_private, the one mode in
which plain http and loopback addresses are called.
"""

from __future__ import annotations

import hashlib
import hmac
import json
import shutil
import socket
import ssl
import subprocess
import threading
import time
from datetime import datetime
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import httpcore
import httpx
import pytest
from stack import assert_error, make_settings, post, sphere_points, wait_final, wp, xyz_bytes

from fastmesh_jobs.runtime import wait_for
from fastmesh_jobs.store import Store
from service.errors import ApiError
from service.processes import ServedApp
from service.submission import webhook_of
from service.webhooks import _CLAIM, UnsafeUrl, attempt, is_public, sign, vet
from service.webhooks import post as post_hook

SECRET = "test-webhook-secret"
BALL = xyz_bytes(sphere_points())


class Receiver:
    """An HTTP server on 127.0.0.1 answering each POST with the next of ``statuses`` (the last one repeats)
    and recording ``(headers, body)`` of every POST."""

    def __init__(self, statuses=(200,)):
        self.statuses = list(statuses)
        self.calls: list[tuple[dict, bytes]] = []
        receiver = self

        class Handler(BaseHTTPRequestHandler):
            def do_POST(self):
                body = self.rfile.read(int(self.headers["Content-Length"]))
                receiver.calls.append(({k.lower(): v for k, v in self.headers.items()}, body))
                status = receiver.statuses[min(len(receiver.calls), len(receiver.statuses)) - 1]
                self.send_response(status)
                self.send_header("Content-Length", "0")
                self.end_headers()

            def log_message(self, *args):
                pass

        self.server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self.server.server_port}/hook"
        threading.Thread(target=self.server.serve_forever, daemon=True).start()

    def close(self):
        self.server.shutdown()
        self.server.server_close()


def hooks_settings(redis_url, name, **kw):
    return make_settings(redis_url, name, webhook_secret=SECRET, webhook_allow_private=True,
                         webhook_backoff_seconds=0.2, webhook_max_attempts=3, **kw)


@pytest.fixture(scope="module")
def idle(redis_url):
    """An app with no worker (jobs stay queued until a test finishes them)."""
    app = ServedApp(hooks_settings(redis_url, "hooks-idle"))
    yield app
    app.stop()


@pytest.fixture()
def receiver():
    r = Receiver()
    yield r
    r.close()


def verified(call) -> dict:
    """The body of a received delivery, after checking its signature the way a receiver would."""
    headers, body = call
    expected = "sha256=" + hmac.new(SECRET.encode(), body, hashlib.sha256).hexdigest()
    assert hmac.compare_digest(headers["x-fastmesh-signature"], expected), headers
    assert headers["content-type"] == "application/json"
    return json.loads(body)


def settled(url: str, job_id: str) -> dict:
    """The job once its webhook is delivered or given up."""
    def done():
        j = httpx.get(f"{url}/v1/jobs/{job_id}", timeout=10).json()
        return j["webhook"]["state"] in ("delivered", "failed") and j
    return wait_for(done, 30, 0.05, what=f"the webhook of job {job_id}")


# ---------------------------------------------------------------- checking URLs (no network: fake resolvers)
def fixed(*addresses):
    return lambda host, port: list(addresses)


@pytest.mark.parametrize("url, why", [
    ("http://example.com/h", "https"),
    ("ftp://example.com/h", "https"),
    ("https:///h", "no host"),
    ("https://user:pw@example.com/h", "credentials"),
    ("https://example.com:99999/h", "not a URL"),
    ("https://example.com/" + "a" * 2000, "longer"),
])
def test_malformed_or_plain_http_urls_are_refused(url, why):
    with pytest.raises(UnsafeUrl, match=why):
        vet(url, False, fixed("93.184.216.34"))


@pytest.mark.parametrize("address", ["127.0.0.1", "10.1.2.3", "172.16.0.9", "192.168.1.1", "169.254.169.254",
                                     "100.64.0.1", "0.0.0.0", "224.0.0.1", "::1", "fe80::1", "fc00::5",
                                     "::ffff:127.0.0.1", "::ffff:10.0.0.1"])
def test_non_public_addresses_are_refused(address):
    assert not is_public(address)
    with pytest.raises(UnsafeUrl, match="non-public"):
        vet("https://hooks.example.com/x", False, fixed(address))
    # Every address counts: one public address beside a private one does not let the name through.
    with pytest.raises(UnsafeUrl, match="non-public"):
        vet("https://hooks.example.com/x", False, fixed("93.184.216.34", address))
    assert vet("https://hooks.example.com/x", True, fixed(address)) == ("hooks.example.com", 443, address)


def test_public_https_url_passes_and_real_names_are_resolved():
    assert vet("https://hooks.example.com:8443/x?a=1", False, fixed("93.184.216.34", "2606:2800:220:1::")) \
        == ("hooks.example.com", 8443, "93.184.216.34")
    with pytest.raises(UnsafeUrl, match="127.0.0.1|::1"):  # the system resolver: localhost is loopback
        vet("https://localhost/x", False)
    with pytest.raises(UnsafeUrl, match="non-public"):  # a literal address is checked too
        vet("https://[::1]:8443/x", False)


def test_submission_refuses_a_bad_callback_url(idle, redis_url):
    r = post(idle.url, "ball.xyz", BALL, callback_url="ftp://example.com/x")
    assert assert_error(r, 422, "invalid_parameter")["message"].startswith("callback_url: must be an https")
    assert Store(idle.settings).redis.zcard(f"{idle.settings.redis_prefix}:queued") == 0  # no job made
    strict = make_settings(redis_url, "hooks-strict", webhook_secret=SECRET)  # what the route asks (submission)
    for url in ("http://127.0.0.1:9/x", "https://127.0.0.1/x", "https://localhost/x", "https://10.0.0.1/x"):
        with pytest.raises(ApiError) as e:
            webhook_of(strict, url)
        assert e.value.status == 422 and e.value.message.startswith("callback_url: "), url
    with pytest.raises(ApiError) as e:
        webhook_of(make_settings(redis_url, "hooks-off"), "https://example.com/x")
    assert e.value.code == "webhooks_disabled" and "FASTMESH_WEBHOOK_SECRET" in e.value.message


# ---------------------------------------------------------------- delivery
def test_success_is_posted_signed(redis_url, weights, tmp_path, receiver):
    s = hooks_settings(redis_url, "hooks-run", weights=weights)
    app = ServedApp(s)
    worker = wp(s, "hooks-w", tmp_path / "w.log").wait_ready()
    try:
        r = post(app.url, "ball.xyz", BALL, callback_url=receiver.url, max_vertices=12)
        assert r.status_code == 202, r.text
        job = r.json()
        assert job["webhook"] == {"url": receiver.url, "state": "waiting", "attempts": 0, "last_status": None,
                                  "last_error": None, "last_attempt_at": None, "next_attempt_at": None}
        assert wait_final(app.url, job["id"])["status"] == "succeeded"
        final = settled(app.url, job["id"])
        assert len(receiver.calls) == 1
        body = verified(receiver.calls[0])
        assert body["id"] == job["id"] and body["status"] == "succeeded" and body["result"]["faces"] > 0
        assert receiver.calls[0][0]["x-fastmesh-event"] == "job.succeeded"
        hook = final["webhook"]
        assert hook["state"] == "delivered" and hook["attempts"] == 1 and hook["last_status"] == 200, hook
    finally:
        worker.stop()
        app.stop()


def test_cancel_is_posted_and_failures_are_retried_with_backoff(idle):
    receiver = Receiver(statuses=(500, 503, 204))
    try:
        job = post(idle.url, "ball.xyz", BALL, callback_url=receiver.url).json()
        time.sleep(0.5)
        assert receiver.calls == []  # nothing before the job finishes
        assert httpx.delete(f"{idle.url}/v1/jobs/{job['id']}").json()["status"] == "cancelled"
        hook = settled(idle.url, job["id"])["webhook"]
        assert hook["state"] == "delivered" and hook["attempts"] == 3 and hook["last_status"] == 204, hook
        assert len(receiver.calls) == 3
        bodies = [verified(c) for c in receiver.calls]
        assert all(b["status"] == "cancelled" for b in bodies)
        # Each body is the job as it stood: the attempts before it and the answer of the last one.
        assert [b["webhook"]["attempts"] for b in bodies] == [0, 1, 2]
        assert bodies[2]["webhook"]["last_status"] == 503
        # The backoff: 0.2 s before the second attempt, 0.4 s before the third.
        t = [datetime.fromisoformat(b["webhook"]["last_attempt_at"]) for b in bodies[1:]] + \
            [datetime.fromisoformat(hook["last_attempt_at"])]
        assert (t[1] - t[0]).total_seconds() >= 0.2 and (t[2] - t[1]).total_seconds() >= 0.4, t
    finally:
        receiver.close()


def test_failure_is_posted_and_given_up_after_max_attempts(idle):
    receiver = Receiver(statuses=(500,))
    try:
        job = post(idle.url, "ball.xyz", BALL, callback_url=receiver.url).json()
        store = Store(idle.settings)
        # The steps a worker takes on a job that fails.
        assert store.start(job["id"], 1, "test-worker")
        assert store.finish(job["id"], 1, "failed", error={"code": "unreadable", "message": "test"})
        hook = settled(idle.url, job["id"])["webhook"]
        assert hook["state"] == "failed" and hook["attempts"] == 3, hook
        assert hook["last_status"] == 500 and "500" in hook["last_error"]
        assert len(receiver.calls) == 3 and verified(receiver.calls[0])["status"] == "failed"
        assert store.redis.zscore(store.k_webhooks, job["id"]) is None  # nothing left queued
    finally:
        receiver.close()


def test_a_delivery_outlives_the_api_process(redis_url):
    """A job that ends while no API process runs (a worker finished it) is delivered by the next one to start,
    and an entry claimed by a dispatcher that died comes due again when its lease runs out."""
    s = hooks_settings(redis_url, "hooks-restart")
    receiver = Receiver()
    store = Store(s)
    job = {"id": store.create("anonymous", {}, {"filename": "x.xyz"}, b"", 0.0,
                              webhook=webhook_of(s, receiver.url))}  # the job POST /v1/jobs makes
    assert store.start(job["id"], 1, "test-worker")
    assert store.finish(job["id"], 1, "succeeded", result={"vertices": 3, "faces": 1})
    # A dispatcher claimed it and died: due again only when the lease ends.
    lease_end = time.time() + 2.0
    assert store.redis.eval(_CLAIM, 1, store.k_webhooks, job["id"], time.time(), lease_end)
    second = ServedApp(s)
    try:
        hook = settled(second.url, job["id"])["webhook"]
        assert hook["state"] == "delivered" and datetime.fromisoformat(hook["last_attempt_at"]).timestamp() >= lease_end
        assert len(receiver.calls) == 1 and verified(receiver.calls[0])["status"] == "succeeded"
    finally:
        second.stop()
        receiver.close()


def test_delivery_rechecks_the_address_against_dns_rebinding(redis_url):
    """A name that resolved to a public address at submission and to a loopback one at delivery is not called."""
    s = make_settings(redis_url, "hooks-rebind", webhook_secret=SECRET, webhook_max_attempts=2)
    store = Store(s)
    receiver = Receiver()
    try:
        job_id = store.create("anonymous", {}, {"filename": "x.xyz"}, b"", 0.0, webhook={
            "url": "https://hooks.example.com/x", "state": "waiting", "attempts": 0, "last_status": None,
            "last_error": None, "last_attempt_at": None, "next_attempt_at": None})
        assert store.cancel(job_id)
        assert store.redis.zscore(store.k_webhooks, job_id) == 0  # queued with the final status
        assert attempt(store, job_id, fixed("127.0.0.1")) == "retry"
        hook = store.get(job_id)["webhook"]
        assert hook["attempts"] == 1 and hook["last_status"] is None and "non-public" in hook["last_error"], hook
        assert hook["state"] == "retrying" and hook["next_attempt_at"] is not None
        assert receiver.calls == []
        assert attempt(store, job_id, fixed("127.0.0.1")) == "failed"
        assert store.redis.zscore(store.k_webhooks, job_id) is None
        assert attempt(store, job_id) == "dropped"  # settled: never delivered again
    finally:
        receiver.close()
        store.delete(job_id)


def test_signature_is_hmac_sha256_of_the_raw_body():
    body = b'{"id":"x"}'
    assert sign("k", body) == "sha256=" + hmac.new(b"k", body, hashlib.sha256).hexdigest()


class RawReceiver:
    """A TCP server on 127.0.0.1 that takes one connection, reads the request's head (unless not
    ``read_first``: a TLS server reads it itself) and then runs ``answer(connection)``."""

    def __init__(self, answer, read_first: bool = True):
        self.sock = socket.create_server(("127.0.0.1", 0))
        self.url = f"http://127.0.0.1:{self.sock.getsockname()[1]}/hook"

        def serve():
            conn, _ = self.sock.accept()
            with conn:
                try:
                    if read_first:
                        conn.recv(65536)
                    answer(conn)
                except OSError:  # the client hung up, as it should (ssl.SSLError included)
                    pass
        threading.Thread(target=serve, daemon=True).start()

    def close(self):
        self.sock.close()


def test_a_receiver_answering_a_byte_at_a_time_is_cut_off_at_the_timeout(redis_url):
    def drip(conn):
        for b in b"HTTP/1.1 200 OK\r\nContent-Length: 0\r\n\r\n":
            conn.sendall(bytes([b]))
            time.sleep(0.2)  # each byte well within the timeout; the whole answer 7 s

    receiver = RawReceiver(drip)
    s = hooks_settings(redis_url, "hooks-drip", webhook_timeout_seconds=1.0)
    t0 = time.monotonic()
    try:
        with pytest.raises(httpcore.TimeoutException):
            post_hook(receiver.url, b"{}", {}, s)
        assert time.monotonic() - t0 < 2.5
    finally:
        receiver.close()


def test_a_large_answer_is_not_read(redis_url):
    def flood(conn):
        conn.sendall(b"HTTP/1.1 200 OK\r\nContent-Length: 10000000000\r\n\r\n")
        chunk = b"x" * 65536
        while True:
            conn.sendall(chunk)

    receiver = RawReceiver(flood)
    try:
        assert post_hook(receiver.url, b"{}", {}, hooks_settings(redis_url, "hooks-flood")) == 200
    finally:
        receiver.close()


def test_delivery_connects_to_the_checked_address(redis_url, receiver):
    """The name is resolved once per attempt, by the check: the connection goes to the address checked, with the
    name in Host (a name the system resolver does not know reaches the receiver through the checked address)."""
    port = receiver.server.server_port
    status = post_hook(f"http://hooks.invalid:{port}/hook", b"{}", {}, hooks_settings(redis_url, "hooks-pin"),
                       fixed("127.0.0.1"))
    assert status == 200 and receiver.calls[0][0]["host"] == f"hooks.invalid:{port}"


@pytest.mark.skipif(shutil.which("openssl") is None, reason="needs the openssl command to make a certificate")
def test_tls_to_the_checked_address_verifies_the_name(redis_url, tmp_path, monkeypatch):
    """Over https the checked address is called with the URL's name in SNI, and the certificate is verified
    against that name: a certificate for it passes, an untrusted one fails."""
    subprocess.run(["openssl", "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "1", "-subj",
                    "/CN=hooks.invalid", "-addext", "subjectAltName=DNS:hooks.invalid", "-keyout",
                    str(tmp_path / "key.pem"), "-out", str(tmp_path / "cert.pem")], check=True, capture_output=True)
    server_ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    server_ctx.load_cert_chain(tmp_path / "cert.pem", tmp_path / "key.pem")
    names = []
    server_ctx.sni_callback = lambda sock, name, ctx: names.append(name)

    def answer(conn):
        with server_ctx.wrap_socket(conn, server_side=True) as tls:
            request = b""
            while not request.endswith(b"\r\n\r\n{}"):  # the whole request (the body is b"{}")
                chunk = tls.recv(65536)
                if not chunk:
                    return
                request += chunk
            tls.sendall(b"HTTP/1.1 204 No Content\r\n\r\n")

    s = hooks_settings(redis_url, "hooks-tls")
    untrusted = RawReceiver(answer, read_first=False)
    try:
        with pytest.raises(httpcore.ConnectError, match="CERTIFICATE_VERIFY_FAILED"):
            post_hook(untrusted.url.replace("http://127.0.0.1", "https://hooks.invalid"), b"{}", {}, s,
                      fixed("127.0.0.1"))
    finally:
        untrusted.close()
    assert names == ["hooks.invalid"]
    trusting = ssl.create_default_context(cafile=str(tmp_path / "cert.pem"))
    monkeypatch.setattr("service.webhooks.httpx.create_ssl_context", lambda: trusting)
    trusted = RawReceiver(answer, read_first=False)
    try:
        url = trusted.url.replace("http://127.0.0.1", "https://hooks.invalid")
        assert post_hook(url, b"{}", {}, s, fixed("127.0.0.1")) == 204
    finally:
        trusted.close()
