"""Preview rendering in child processes, so the API's memory stays flat whatever the input's size.

A preview of a dense input decodes tens of MB and rasterises it; done in the API process, the
allocator keeps what a burst of them took.  Here each render runs in one of a few ``spawn``-ed
processes (recycled after :data:`TASKS_PER_CHILD` renders), and the API holds only the stored
bytes going in and the PNG coming out.  This module imports no web framework: it is what a child
imports.
"""

from __future__ import annotations

import multiprocessing
import os
import threading
import time
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool

TASKS_PER_CHILD = 50  # a child is replaced after this many renders: what its allocator kept goes with it
ORPHAN_CHECK_SECONDS = 1.0  # how often a render process checks that the API process still exists
RENDER_NICENESS = 10  # renders yield the CPU to the API process, so status polls stay fast during a burst


def _background() -> None:
    """Initializer of a render process: low priority, and gone with the API process.  An API killed
    without its shutdown (SIGKILL, a crash) cannot stop its children, so each watches its parent."""
    os.nice(RENDER_NICENESS)
    parent = os.getppid()

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(ORPHAN_CHECK_SECONDS)
        os._exit(0)

    threading.Thread(target=watch, name="fastmesh-render-orphan-watch", daemon=True).start()


def render_blob(of: str, blob: bytes, size: int, wireframe: bool) -> bytes:
    """PNG bytes of a stored result (``of == "result"``: npz of vertices and faces) or input (a Shape's npz).

    A result without faces (a degenerate generation) is drawn as its vertices, so the preview still
    shows what came out.  Raises :class:`fastmesh.io.ShapeError` when there is nothing drawable.
    """
    from fastmesh.render import render_mesh, render_points, render_shape, to_png

    from .store import mesh_from_bytes, shape_from_bytes

    if of == "result":
        vertices, faces = mesh_from_bytes(blob)
        img = render_mesh(vertices, faces, size=size, wireframe=wireframe) if len(faces) else \
            render_points(vertices, size=size)
    else:
        shape = shape_from_bytes(blob)
        img = render_shape(shape, size=size, wireframe=wireframe and shape.faces is not None)
    return to_png(img)


class RenderPool:
    """``workers`` render processes, started on first use; :meth:`close` stops them."""

    def __init__(self, workers: int):
        self.workers = workers
        self._pool: ProcessPoolExecutor | None = None
        self._lock = threading.Lock()

    def render(self, of: str, blob: bytes, size: int, wireframe: bool, timeout: float) -> bytes:
        with self._lock:
            if self._pool is None:
                self._pool = ProcessPoolExecutor(self.workers, mp_context=multiprocessing.get_context("spawn"),
                                                 max_tasks_per_child=TASKS_PER_CHILD, initializer=_background)
            pool = self._pool
        try:
            return pool.submit(render_blob, of, blob, size, wireframe).result(timeout)
        except BrokenProcessPool:  # a child died (killed, out of memory): the next render starts new ones
            with self._lock:
                if self._pool is pool:
                    self._pool = None
            pool.shutdown(wait=False, cancel_futures=True)
            raise

    def close(self) -> None:
        """Stop the render processes (a render under way finishes first)."""
        with self._lock:
            pool, self._pool = self._pool, None
        if pool is not None:
            pool.shutdown(wait=True, cancel_futures=True)
