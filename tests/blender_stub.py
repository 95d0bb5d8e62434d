"""A stand-in FastMesh service over real HTTP for the Blender add-on's tests (tests/test_blender_client.py):
the job routes with the service's JSON shapes and error body, scripted outcomes, and a record of what each
request sent.  A finished job's result is the upload itself (OBJ as uploaded; GLB converted by trimesh), moved
as ``origin`` asks, so a test can check where an imported result lands.
"""

from __future__ import annotations

import email.parser
import email.policy
import io
import json
import threading
import time
import uuid
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from urllib.parse import parse_qs, urlsplit

import numpy as np
import trimesh


class Stub:
    """The service's behaviour, set by a test before it sends: ``outcome`` (succeeded, failed, or running for
    ever), ``reject`` (an error answer for every submission: ``(status, body bytes, headers)``), ``busy``
    (429 answers before the first accepted submission), ``slow`` (seconds each answer waits), ``key``; a job
    sent with a seed of ``seed_outcomes`` ends so whatever ``outcome`` says, one with ``seed=broken_seed`` has
    a GLB no importer reads."""

    def __init__(self):
        self.outcome = "succeeded"
        self.reject: tuple[int, bytes, dict] | None = None
        self.busy = 0
        self.slow = 0.0
        self.key: str | None = None
        self.polls_to_finish = 3
        self.seed_outcomes = {"13": "failed", "99": "running"}
        self.broken_seed = "7"
        self.submissions: list[dict] = []  # {"fields", "filename", "data", "headers"}
        self.downloads: list[str] = []  # formats asked for
        self.cancelled: list[str] = []
        self.jobs: dict[str, dict] = {}
        self.lock = threading.Lock()

    def job_json(self, job_id: str) -> dict:
        j = self.jobs[job_id]
        outcome = self.seed_outcomes.get(j["fields"].get("seed"), self.outcome)
        stages = [("queued", "queued", 0.0), ("running", "vertices", 0.4), ("running", "faces", 0.8)]
        if j["cancelled"]:
            status, stage, frac = "cancelled", "cancelled", j["fraction"]
        elif j["polls"] >= self.polls_to_finish and outcome != "running":
            status, stage, frac = outcome, "done" if outcome == "succeeded" else "failed", 1.0
        else:
            status, stage, frac = stages[min(j["polls"], len(stages) - 1)]
        j["fraction"] = frac
        error = {"code": "generation_failed", "message": "the model made no faces"} if status == "failed" else None
        result = {"vertices": 8, "faces": 12} if status == "succeeded" else None
        return {"id": job_id, "status": status, "progress": {"stage": stage, "fraction": frac},
                "params": j["fields"], "result": result, "error": error}


def parse_form(content_type: str, body: bytes) -> tuple[dict, str, bytes]:
    """``(fields, filename, file bytes)`` of a multipart/form-data body, read by the standard email parser (an
    implementation independent of the add-on's writer)."""
    msg = email.parser.BytesParser(policy=email.policy.HTTP).parsebytes(
        f"Content-Type: {content_type}\r\n\r\n".encode() + body)
    fields, filename, data = {}, None, None
    for part in msg.iter_parts():
        name = part.get_param("name", header="content-disposition")
        if part.get_filename() is not None:
            filename, data = part.get_filename(), part.get_payload(decode=True)
        else:
            fields[name] = part.get_payload(decode=True).decode()
    return fields, filename, data


def result_of(sub: dict, fmt: str) -> bytes:
    """The upload (an OBJ) back as ``fmt``, moved as the submission's ``origin`` asks (in the file's Y-up
    frame), as the service does: OBJ with its polygons kept (turned Z-up for ``up=z``), or GLB (always Y-up)."""
    lines = sub["data"].decode().splitlines()
    v = np.array([[float(t) for t in ln.split()[1:4]] for ln in lines if ln.startswith("v ")])
    lo, hi = v.min(axis=0), v.max(axis=0)
    origin = sub["fields"].get("origin")
    shift = np.zeros(3)
    if origin == "center":
        shift = -(lo + hi) / 2
    elif origin == "bottom":
        shift = -np.array([(lo[0] + hi[0]) / 2, lo[1], (lo[2] + hi[2]) / 2])
    if fmt == "obj":
        moved = v + shift
        if sub["fields"].get("up") == "z":
            moved = moved @ np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]]).T  # (x, y, z) -> (x, -z, y)
        moved = iter(moved)
        return "".join("v {:.9g} {:.9g} {:.9g}\n".format(*next(moved)) if ln.startswith("v ") else ln + "\n"
                       for ln in lines).encode()
    mesh = trimesh.load(io.BytesIO(sub["data"]), file_type="obj", process=False)
    mesh.apply_translation(shift)
    return mesh.export(file_type="glb")


def error_body(code: str, message: str) -> bytes:
    return json.dumps({"error": {"code": code, "message": message}}).encode()


class Handler(BaseHTTPRequestHandler):
    stub: Stub

    def log_message(self, *args):  # quiet test output
        pass

    def answer(self, status: int, body: bytes, ctype: str = "application/json", headers: dict | None = None):
        self.send_response(status)
        self.send_header("Content-Type", ctype)
        self.send_header("Content-Length", str(len(body)))
        for k, v in (headers or {}).items():
            self.send_header(k, v)
        self.end_headers()
        self.wfile.write(body)

    def authorised(self) -> bool:
        if self.stub.key and self.headers.get("Authorization") != f"Bearer {self.stub.key}":
            self.answer(401, error_body("unauthorized", "missing or unknown API key"))
            return False
        time.sleep(self.stub.slow)
        return True

    def do_POST(self):
        body = self.rfile.read(int(self.headers.get("Content-Length", 0)))
        if not self.authorised():
            return
        s = self.stub
        if urlsplit(self.path).path != "/v1/jobs":
            return self.answer(404, error_body("not_found", "no such route"))
        if s.reject:
            return self.answer(s.reject[0], s.reject[1], headers=s.reject[2])
        with s.lock:
            if s.busy:
                s.busy -= 1
                return self.answer(429, error_body("queue_full", "3 jobs are waiting"), headers={"Retry-After": "0"})
            fields, filename, data = parse_form(self.headers["Content-Type"], body)
            job_id = uuid.uuid4().hex
            s.submissions.append({"fields": fields, "filename": filename, "data": data,
                                  "headers": dict(self.headers)})
            s.jobs[job_id] = {"polls": 0, "fields": fields, "cancelled": False, "fraction": 0.0,
                              "sub": s.submissions[-1]}
            self.answer(202, json.dumps(s.job_json(job_id)).encode())

    def do_GET(self):
        if not self.authorised():
            return
        s, url = self.stub, urlsplit(self.path)
        parts = url.path.strip("/").split("/")
        if parts[:2] != ["v1", "jobs"] or len(parts) < 3 or parts[2] not in s.jobs:
            return self.answer(404, error_body("not_found", "no such job"))
        with s.lock:
            job = s.jobs[parts[2]]
            if len(parts) == 3:
                job["polls"] += 1
                return self.answer(200, json.dumps(s.job_json(parts[2])).encode())
            fmt = parse_qs(url.query).get("format", ["glb"])[0]
            s.downloads.append(fmt)
            broken = fmt == "glb" and job["fields"].get("seed") == s.broken_seed
            data = b"glTF\x02\x00\x00\x00 not a GLB" if broken else result_of(job["sub"], fmt)
            self.answer(200, data, "application/octet-stream")

    def do_DELETE(self):
        if not self.authorised():
            return
        s = self.stub
        job_id = urlsplit(self.path).path.rstrip("/").rsplit("/", 1)[-1]
        with s.lock:
            if job_id not in s.jobs:
                return self.answer(404, error_body("not_found", "no such job"))
            s.cancelled.append(job_id)
            s.jobs[job_id]["cancelled"] = True
            self.answer(200, json.dumps(s.job_json(job_id)).encode())


class StubServer:
    """:class:`Stub` served on a free local port in a background thread; ``url`` is its base URL."""

    def __init__(self):
        self.stub = Stub()
        handler = type("BoundHandler", (Handler,), {"stub": self.stub})
        self.server = ThreadingHTTPServer(("127.0.0.1", 0), handler)
        self.server.daemon_threads = True
        self.url = f"http://127.0.0.1:{self.server.server_address[1]}"
        self.thread = threading.Thread(target=self.server.serve_forever, daemon=True)
        self.thread.start()

    def close(self) -> None:
        self.server.shutdown()
        self.server.server_close()
