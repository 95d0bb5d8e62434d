"""HTTP and file logic of the FastMesh Blender add-on: the standard library only (Blender's Python has no
third-party packages) and no ``bpy``, so it runs and is tested outside Blender.

    c = Client("http://127.0.0.1:8000", api_key="...")
    task = Task(c, "chair.obj", obj_bytes(vertices, faces), {"target_faces": 500, "topology": None})
    task.start()            # submit, poll, download in a background thread
    task.snapshot()         # read from the UI thread: state, stage, fraction, message, result bytes

Errors of the service (its JSON ``{"error": {"code", "message"}}``), an unreachable or malformed URL and a
timeout all raise :class:`ServiceError` with a ``status`` (0 when no answer came), a ``code`` and a message
for people.
"""

from __future__ import annotations

import json
import math
import threading
import urllib.error
import urllib.parse
import urllib.request
import uuid
from collections.abc import Iterable, Mapping, Sequence

FINAL = ("succeeded", "failed", "cancelled")
# The fields the panel offers, with the values each takes (fastmesh.params, the service's form); numbers
# are checked by the service, which names the field in its 422.
CHOICES = {"topology": ("triangle", "quad"), "uv": ("true", "false"), "origin": ("input", "center", "bottom"),
           "up": ("y", "z"), "closed": ("auto", "true", "false")}
POLL_SECONDS = 0.5  # first wait between status reads; it grows 1.3x a read up to max_poll
RETRY_429 = 5  # queue full or rate limited: waits of the service's Retry-After before giving up
MAX_RETRY_AFTER = 60.0


class ServiceError(RuntimeError):
    """An error answer of the service, or no answer (``status`` 0: ``bad_url``, ``unreachable``, ``timeout``)."""

    def __init__(self, status: int, code: str, message: str, retry_after: float | None = None):
        super().__init__(f"{message} ({code}, HTTP {status})" if status else message)
        self.status, self.code, self.message, self.retry_after = status, code, message, retry_after


def base_url(url: str) -> str:
    """``url`` without a trailing slash.  Raises ServiceError ``bad_url`` unless it is http(s)://host[:port]."""
    text = (url or "").strip()
    try:
        parts = urllib.parse.urlsplit(text)
        parts.port  # noqa: B018 -- reading it validates the port
    except ValueError as e:
        raise ServiceError(0, "bad_url", f"'{text[:80]}' is not a valid URL: {e}") from None
    if parts.scheme not in ("http", "https") or not parts.hostname:
        raise ServiceError(0, "bad_url", f"'{text[:80]}' is not an http:// or https:// URL with a host "
                                         "(e.g. http://127.0.0.1:8000)")
    return text.rstrip("/")


def form_fields(params: Mapping[str, object]) -> dict[str, str]:
    """The form fields of ``params`` as the service spells them, leaving out every unset (None) one: a
    server that predates a field then still accepts a request that does not use it.

    Raises
    ------
    ValueError
        A choice outside :data:`CHOICES` or a number that is not finite, naming the field.
    """
    out = {}
    for name, value in params.items():
        if value is None:
            continue
        if isinstance(value, bool):
            text = "true" if value else "false"
        elif isinstance(value, float):
            if not math.isfinite(value):
                raise ValueError(f"{name}: must be a finite number")
            text = repr(value)  # shortest exact spelling; the service refuses lax ones
        else:
            text = str(value)
        if name in CHOICES and text not in CHOICES[name]:
            raise ValueError(f"{name}: '{text}' is not one of {', '.join(CHOICES[name])}")
        out[name] = text
    return out


def multipart(fields: Mapping[str, str], filename: str, data: bytes) -> tuple[bytes, str]:
    """``(body, Content-Type)`` of a multipart/form-data request with ``fields`` and the file part ``file``."""
    boundary = f"fastmesh-{uuid.uuid4().hex}"
    safe = filename.replace('"', "_").replace("\r", "_").replace("\n", "_")
    parts = []
    for name, value in fields.items():
        parts.append(f'--{boundary}\r\nContent-Disposition: form-data; name="{name}"\r\n\r\n{value}\r\n'.encode())
    parts.append(f'--{boundary}\r\nContent-Disposition: form-data; name="file"; filename="{safe}"\r\n'
                 f"Content-Type: application/octet-stream\r\n\r\n".encode())
    parts.append(data)
    parts.append(f"\r\n--{boundary}--\r\n".encode())
    return b"".join(parts), f"multipart/form-data; boundary={boundary}"


def error_of(status: int, body: bytes, headers: Mapping[str, str] | None = None) -> ServiceError:
    """The ServiceError of an error answer: the service's JSON code and message, else the start of the body."""
    retry = None
    if headers is not None and headers.get("Retry-After"):
        try:
            retry = min(MAX_RETRY_AFTER, max(0.0, float(headers["Retry-After"])))
        except ValueError:
            retry = None
    try:
        err = json.loads(body)["error"]
        return ServiceError(status, str(err["code"]), str(err["message"]), retry)
    except (ValueError, KeyError, TypeError):
        text = body[:200].decode("utf-8", "replace").strip() or "no detail"
        return ServiceError(status, "http_error", f"HTTP {status} from the service: {text}", retry)


class Client:
    """Blocking calls of the FastMesh HTTP API (run them off Blender's UI thread: :class:`Task`).

    ``timeout`` bounds each request's connect and each read, in seconds.
    """

    def __init__(self, url: str, api_key: str | None = None, timeout: float = 60.0):
        self.url = base_url(url)
        self.headers = {"Authorization": f"Bearer {api_key}"} if api_key else {}
        self.timeout = timeout

    def request(self, method: str, path: str, body: bytes | None = None,
                headers: Mapping[str, str] | None = None) -> bytes:
        """The answer's body.  Raises ServiceError for an error answer, no answer or a timeout."""
        req = urllib.request.Request(self.url + path, data=body, method=method,
                                     headers={**self.headers, **(headers or {})})
        try:
            with urllib.request.urlopen(req, timeout=self.timeout) as r:
                return r.read()
        except urllib.error.HTTPError as e:
            try:
                body = e.read()
            except OSError:
                body = b""
            finally:
                e.close()
            raise error_of(e.code, body, e.headers) from None
        except TimeoutError:
            raise ServiceError(0, "timeout", f"no answer from {self.url} within {self.timeout:g} s") from None
        except urllib.error.URLError as e:
            if isinstance(e.reason, TimeoutError):
                raise ServiceError(0, "timeout", f"no answer from {self.url} within {self.timeout:g} s") from None
            raise ServiceError(0, "unreachable", f"cannot reach {self.url}: {e.reason}") from None
        except (OSError, ValueError) as e:  # a connection reset mid-answer, a malformed answer
            raise ServiceError(0, "unreachable", f"cannot reach {self.url}: {e}") from None

    def json(self, method: str, path: str, **kw) -> dict:
        data = self.request(method, path, **kw)
        try:
            return json.loads(data)
        except ValueError:
            raise ServiceError(0, "bad_answer", f"{self.url}{path} did not answer JSON; is this a FastMesh "
                                                "service?") from None

    def submit(self, filename: str, data: bytes, params: Mapping[str, object]) -> dict:
        """``POST /v1/jobs``: the queued job.  ``params`` as :func:`form_fields` takes them."""
        body, ctype = multipart(form_fields(params), filename, data)
        # The same key on a retry returns the same job rather than a second one.
        return self.json("POST", "/v1/jobs", body=body,
                         headers={"Content-Type": ctype, "Idempotency-Key": uuid.uuid4().hex})

    def job(self, job_id: str) -> dict:
        return self.json("GET", f"/v1/jobs/{urllib.parse.quote(job_id)}")

    def result(self, job_id: str, fmt: str = "glb") -> bytes:
        return self.request("GET", f"/v1/jobs/{urllib.parse.quote(job_id)}/result?format={fmt}")

    def cancel(self, job_id: str) -> None:
        self.request("DELETE", f"/v1/jobs/{urllib.parse.quote(job_id)}")


class Task:
    """One job from upload to result bytes, in a background thread so Blender's UI never waits on the network.

    The UI thread reads :meth:`snapshot` (``state``: submitting, queued, running, downloading, done, failed,
    cancelled; ``stage``, ``fraction``, ``message``, ``job``, ``result``) and may call :meth:`cancel`.
    """

    def __init__(self, client: Client, filename: str, data: bytes, params: Mapping[str, object],
                 fmt: str = "glb", poll: float | None = None, max_poll: float = 2.0):
        self.client, self.filename, self.data, self.fmt = client, filename, data, fmt
        self.params = {**params, "formats": fmt}
        self.poll, self.max_poll = POLL_SECONDS if poll is None else poll, max_poll
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._state = {"state": "submitting", "stage": None, "fraction": 0.0, "message": "uploading",
                       "job": None, "result": None, "error": None}
        self._thread: threading.Thread | None = None
        self._job: dict | None = None  # a job submitted before: only its result is fetched

    @classmethod
    def download(cls, client: Client, job: dict, fmt: str) -> Task:
        """A task that fetches the result of the finished ``job`` in ``fmt`` (no upload)."""
        task = cls(client, "", b"", {}, fmt=fmt)
        task._job = job
        task._set(state=job["status"], message=f"downloading the result as {fmt}", job=job)
        return task

    def start(self) -> Task:
        self._thread = threading.Thread(target=self.run, name="fastmesh-task", daemon=True)
        self._thread.start()
        return self

    def snapshot(self) -> dict:
        with self._lock:
            return dict(self._state)

    def finished(self) -> bool:
        return self.snapshot()["state"] in ("done", "failed", "cancelled")

    def cancel(self) -> None:
        """Stop polling and cancel the job on the service (from any thread)."""
        self._stop.set()

    def join(self, timeout: float | None = None) -> None:
        if self._thread is not None:
            self._thread.join(timeout)

    def _set(self, **kw) -> None:
        with self._lock:
            self._state.update(kw)

    def run(self) -> None:
        """Submit, poll until final, download; every outcome ends in a final state with a message."""
        try:
            job = self._job or self._call(self.client.submit, self.filename, self.data, self.params)
            self.data = b""  # the upload is on the service: free Blender's copy
            job = self._follow(job)
            if job is None:
                return
            if job["status"] != "succeeded":
                err = job.get("error") or {}
                self._set(state=job["status"], job=job, error=err.get("code", job["status"]),
                          message=f"job {job['status']}: {err.get('message', 'no detail')}")
                return
            self._set(state="downloading", message="downloading the result", job=job)
            data = self._call(self.client.result, job["id"], self.fmt)
            res = job.get("result") or {}
            self._set(state="done", result=data, fraction=1.0,
                      message=f"done: {res.get('vertices', '?')} vertices, {res.get('faces', '?')} faces")
        except _Cancelled:
            self._set(state="cancelled", message="cancelled")
        except ServiceError as e:
            self._set(state="failed", error=e.code, message=str(e))
        except Exception as e:  # the panel shows it rather than the thread dying silently
            self._set(state="failed", error="client_error", message=f"{type(e).__name__}: {e}")

    def _follow(self, job: dict) -> dict | None:
        """Poll ``job`` until it is final (None when cancelled here, after cancelling it on the service)."""
        interval = self.poll
        while True:
            progress = job.get("progress") or {}
            stage = progress.get("stage")
            self._set(state=job["status"], job=job, stage=stage, fraction=float(progress.get("fraction") or 0.0),
                      message=f"{job['status']}: {stage}" if stage and stage != job["status"] else job["status"])
            if job["status"] in FINAL:
                return job
            if self._stop.wait(interval):
                try:
                    self.client.cancel(job["id"])
                except ServiceError:
                    pass  # it finished meanwhile, or the service is gone: either way nothing runs for us
                raise _Cancelled
            interval = min(self.max_poll, interval * 1.3)
            job = self._call(self.client.job, job["id"])

    def _call(self, fn, *args):
        """``fn(*args)``, waiting out a queue-full or rate-limit answer's Retry-After a few times."""
        for attempt in range(RETRY_429 + 1):
            if self._stop.is_set():
                raise _Cancelled
            try:
                return fn(*args)
            except ServiceError as e:
                if e.status != 429 or attempt == RETRY_429:
                    raise
                wait = 1.0 if e.retry_after is None else e.retry_after
                self._set(message=f"service busy ({e.code}); retrying in {wait:g} s")
                if self._stop.wait(wait):
                    raise _Cancelled from None
        raise AssertionError("unreachable")


class _Cancelled(Exception):
    pass


# ---------------------------------------------------------------------------------------------- files
def blender_to_gltf(x: float, y: float, z: float) -> tuple[float, float, float]:
    """A point of Blender's Z-up frame in glTF's Y-up frame, as Blender's glTF and OBJ exporters write it
    (and their importers read it back), so a result imports upright."""
    return x, z, -y


def obj_bytes(vertices: Iterable[Sequence[float]], faces: Iterable[Sequence[int]]) -> bytes:
    """A Wavefront OBJ of ``vertices`` (V, 3) and polygons ``faces`` (0-based indices, any size >= 3)."""
    lines = ["# FastMesh Blender add-on\n"]
    lines += [f"v {x:.9g} {y:.9g} {z:.9g}\n" for x, y, z in vertices]  # 9 digits: float32 exactly
    lines += ["f " + " ".join(str(i + 1) for i in f) + "\n" for f in faces]
    return "".join(lines).encode()


def xyz_bytes(vertices: Iterable[Sequence[float]]) -> bytes:
    """A point cloud ``vertices`` (N, 3) as text, one ``x y z`` a line."""
    return "".join(f"{x:.9g} {y:.9g} {z:.9g}\n" for x, y, z in vertices).encode()


def upload_of(name: str, vertices: Sequence[Sequence[float]], faces: Sequence[Sequence[int]]) -> tuple[str, bytes]:
    """``(filename, bytes)`` to upload for an object ``name`` with world-space ``vertices`` (V, 3) in Blender's
    frame and ``faces``: an OBJ in glTF's frame, or ``.xyz`` points for an object without faces."""
    stem = "".join(c if c.isalnum() or c in "-_." else "_" for c in name).strip("._") or "object"
    pts = [blender_to_gltf(*v) for v in vertices]
    if not pts:
        raise ValueError(f"{name} has no vertices to send")
    return (f"{stem}.obj", obj_bytes(pts, faces)) if faces else (f"{stem}.xyz", xyz_bytes(pts))


def bounds(vertices: Iterable[Sequence[float]]) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """``(min, max)`` corners of ``vertices`` (V, 3)."""
    pts = list(vertices)
    if not pts:
        raise ValueError("no vertices")
    return tuple(min(p[i] for p in pts) for i in range(3)), tuple(max(p[i] for p in pts) for i in range(3))


def placement(lo: Sequence[float], hi: Sequence[float], origin: str | None) -> tuple[float, float, float]:
    """Where to move an imported result (Blender frame) so it stands beside an original with world bounds
    ``lo``..``hi``: one width along X.  With ``origin`` center or bottom the result's pivot (its object origin)
    goes to the original's bounding-box centre or bottom centre, moved the same width."""
    width = hi[0] - lo[0]
    if origin in (None, "input"):
        return width, 0.0, 0.0
    cx, cy, cz = ((a + b) / 2 for a, b in zip(lo, hi, strict=True))
    return cx + width, cy, cz if origin == "center" else lo[2]


def import_format(params: Mapping[str, object]) -> str:
    """The result format to download: OBJ for quads (the service's GLB holds triangles only), else GLB."""
    return "obj" if params.get("topology") == "quad" else "glb"


def up_correction(up: str | None, fmt: str) -> float:
    """Rotation about X, radians, that stands a result upright after Blender's importer read it as Y-up.

    ``up=z`` turns the service's OBJ and PLY files by (x, y, z) -> (x, -z, y), the very turn Blender's
    importers apply to a Y-up file, so an OBJ comes in turned twice: -90 degrees undoes one.  A GLB is Y-up
    whatever ``up`` says (glTF fixes its up axis): 0."""
    return -math.pi / 2 if up == "z" and fmt == "obj" else 0.0
