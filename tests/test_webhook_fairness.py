"""Webhook deliveries are fair between API keys (service.webhooks.Dispatcher): one key's receivers that hang until
the timeout hold at most ``DELIVERIES_PER_KEY`` delivery threads, and another key's delivery goes out at once.
Receivers on 127.0.0.1 only (the apps set webhook_allow_private)."""

from __future__ import annotations

import socket
import threading
import time
from collections import Counter

import httpx
import pytest
from stack import make_settings, post, sphere_points, xyz_bytes
from test_webhooks import SECRET, Receiver, verified

from fastmesh_jobs.runtime import wait_for
from fastmesh_jobs.store import Store
from service import webhooks
from service.processes import ServedApp
from service.webhooks import DELIVERIES_PER_KEY, Dispatcher, fair_order, new_webhook

BALL = xyz_bytes(sphere_points())
TIMEOUT = 6.0  # webhook_timeout_seconds: how long a hanging receiver holds a delivery


class Hanging:
    """A TCP server on 127.0.0.1 that accepts every connection and never answers; ``conns`` are those held."""

    def __init__(self):
        self.sock = socket.create_server(("127.0.0.1", 0), backlog=64)
        self.url = f"http://127.0.0.1:{self.sock.getsockname()[1]}/hook"
        self.conns: list[socket.socket] = []
        threading.Thread(target=self.serve, daemon=True).start()

    def serve(self):
        while True:
            try:
                conn, _ = self.sock.accept()
            except OSError:  # closed
                return
            self.conns.append(conn)

    def close(self):
        self.sock.close()
        for conn in self.conns:
            conn.close()


@pytest.fixture()
def two_keys(redis_url):
    s = make_settings(redis_url, "hooks-fair", api_keys=["key-a", "key-b"], webhook_secret=SECRET,
                      webhook_allow_private=True, webhook_max_attempts=1, webhook_timeout_seconds=TIMEOUT)
    app = ServedApp(s)
    yield app
    app.stop()


def submit_and_cancel(app, key: str, url: str) -> str:
    auth = {"Authorization": f"Bearer {key}"}
    r = post(app.url, "ball.xyz", BALL, headers=auth, callback_url=url)
    assert r.status_code == 202, r.text
    job_id = r.json()["id"]
    assert httpx.delete(f"{app.url}/v1/jobs/{job_id}", headers=auth).json()["status"] == "cancelled"
    return job_id


def test_one_keys_hanging_receivers_do_not_delay_another_keys_delivery(two_keys):
    hanging, receiver = Hanging(), Receiver()
    try:
        for _ in range(8):  # key A: eight deliveries to a receiver that never answers
            submit_and_cancel(two_keys, "key-a", hanging.url)
        wait_for(lambda: len(hanging.conns) >= DELIVERIES_PER_KEY, 10, 0.05, what="key A's deliveries to start")
        t0 = time.monotonic()
        job_b = submit_and_cancel(two_keys, "key-b", receiver.url)  # key B, while A's deliveries hang
        wait_for(lambda: receiver.calls, 3 * TIMEOUT, 0.02, what="key B's delivery")
        waited = time.monotonic() - t0
        assert verified(receiver.calls[0])["id"] == job_b
        # B went out at once (a submission, a cancel and a dispatch), not after A's receivers timed out...
        assert waited < TIMEOUT / 2, f"key B's delivery waited {waited:.2f} s behind key A's hanging receivers"
        # ...and A holds no more than its share of the delivery threads meanwhile.
        assert len(hanging.conns) == DELIVERIES_PER_KEY
    finally:
        hanging.close()
        receiver.close()


def test_keys_take_turns_and_a_busy_key_goes_last():
    due = [("a1", "A"), ("a2", "A"), ("a3", "A"), ("b1", "B"), ("c1", "C")]
    assert [j for _, j, _ in fair_order(due, Counter())] == ["a1", "b1", "c1", "a2", "a3"]
    ranked = fair_order(due, Counter({"B": 3}))
    assert [(rank, j) for rank, j, _ in ranked] == [(0, "a1"), (0, "c1"), (1, "a2"), (2, "a3"), (3, "b1")]


class HeldPool:
    """A pool whose deliveries never run: each stays under way, as one to a hanging receiver does."""

    def __init__(self):
        self.submitted = []

    def submit(self, fn):
        self.submitted.append(fn)


def test_a_key_at_its_limit_makes_way_for_entries_past_the_look(redis_url, monkeypatch):
    """More due entries than one look (SCAN) takes, all of key A's first: A's beyond its limit are put off, so
    key B's entry behind them starts on the next look."""
    monkeypatch.setattr(webhooks, "SCAN", 4)
    monkeypatch.setattr(webhooks, "DELIVERIES_PER_KEY", 2)
    store = Store(make_settings(redis_url, "hooks-scan", webhook_secret=SECRET))
    ids = {}
    for i, owner in enumerate(["A"] * 6 + ["B"]):
        job_id = store.create(owner, {}, {"filename": "x.xyz"}, b"", 0.0, webhook=new_webhook("https://x.invalid/"))
        assert store.cancel(job_id)
        store.redis.zadd(store.k_webhooks, {job_id: i + 1})  # due one after another: A's six, then B's
        ids[job_id] = owner
    try:
        dispatcher = Dispatcher(store, HeldPool())
        assert dispatcher.tick() == 2 and Counter(dispatcher.busy.values()) == {"A": 2}
        assert dispatcher.tick() == 1 and Counter(dispatcher.busy.values()) == {"A": 2, "B": 1}
    finally:
        for job_id in ids:
            store.delete(job_id)
        store.redis.delete(store.k_webhooks)
