"""Work on untrusted bytes in child processes with a hard memory cap and a deadline.

Parsing an upload, sampling a stored input and rendering a preview allocate what the file makes
them allocate, and a parser's amplification (a glTF accessor, a polygon fan, a JSON document of
empty objects) is found one trick at a time.  :class:`CappedPool` runs such work in ``spawn``-ed
processes whose address space is capped with ``RLIMIT_AS``: whatever a file makes a parser do, the
child runs out of memory (``MemoryError``, or dies) and the API process, which holds only the bytes
going in and the answer coming out, stays at its size.  A task that runs past its deadline has its
process killed.  Each child serves tasks one at a time over a pipe and is replaced after
``tasks_per_child`` of them, so what its allocator kept goes with it.

This module imports no web framework and nothing heavy at import time: it is what a child imports.
"""

from __future__ import annotations

import io
import multiprocessing
import os
import pickle
import queue
import threading
import time
from collections.abc import Callable

from fastmesh_jobs.memory import tune_malloc

ORPHAN_CHECK_SECONDS = 1.0  # how often a child checks that the API process still exists
STOP_WAIT_SECONDS = 2.0  # a recycled child gets this long to exit before it is killed
# Imported by a child before its memory is capped, so the cap is spent on the work, not on imports.
PRELOAD = ("numpy", "scipy.spatial", "trimesh", "fastmesh.shapes.io", "fastmesh.shapes.precheck",
           "fastmesh.shapes.pointfiles", "fastmesh.preview.render", "fastmesh.preview.overlay", "fastmesh_jobs.blobs",
           "service.parsing", "service.render_pool")
# One thread per library: every thread reserves address space (stacks, malloc arenas) inside the cap.
THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS")
RETIRE_SHARE = 0.6  # a child whose address space ends a task above this share of its cap is replaced


class ChildFailed(Exception):
    """A task that gave no answer: ``reason`` is ``memory`` (it ran out of its cap), ``deadline`` (it ran
    past its time and was killed), ``crashed`` (its process died) or ``busy`` (no child free in time)."""

    def __init__(self, reason: str, message: str):
        super().__init__(message)
        self.reason, self.message = reason, message


class ChildShapeError(Exception):
    """A :class:`fastmesh.shapes.shape.ShapeError` raised in a child (``code``, ``message``), carried back whole."""

    def __init__(self, code: str, message: str):
        super().__init__(message)
        self.code, self.message = code, message


def _cap_memory(memory_bytes: int) -> None:
    import resource

    resource.setrlimit(resource.RLIMIT_AS, (memory_bytes, memory_bytes))


def _address_space() -> int:
    """This process's virtual size in bytes (what ``RLIMIT_AS`` caps)."""
    with open("/proc/self/statm") as f:
        return int(f.read().split()[0]) * os.sysconf("SC_PAGE_SIZE")


def _watch_parent(parent: int) -> None:
    """End this child when the API process is gone: one killed without its shutdown (SIGKILL, a crash)
    cannot stop its children."""

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(ORPHAN_CHECK_SECONDS)
        os._exit(0)

    threading.Thread(target=watch, name="fastmesh-child-orphan-watch", daemon=True).start()


def _answer(fn: Callable, payload: bytes | None, args: tuple) -> tuple:
    """``fn``'s result or failure as a picklable message."""
    from fastmesh.shapes.shape import ShapeError

    try:
        return ("ok", fn(payload, *args) if payload is not None else fn(*args))
    except ShapeError as e:
        return ("shape", e.code, e.message)
    except MemoryError:
        return ("memory", "")
    except RecursionError:
        return ("shape", "unreadable", "the file nests its structure too deeply to be read")
    except Exception as e:  # the parent words it; the child must go on serving
        return ("error", f"{type(e).__name__}: {str(e)[:300]}")


def serve(conn, memory_bytes: int, niceness: int, parent: int) -> None:
    """A child's loop: receive ``(fn, args, has_payload)`` [+ payload bytes], send the answer; None ends it."""
    for var in THREAD_VARS:
        os.environ[var] = "1"
    if niceness:
        os.nice(niceness)
    tune_malloc()
    _watch_parent(parent)
    import importlib

    for name in PRELOAD:
        importlib.import_module(name)
    _cap_memory(memory_bytes)
    while True:
        try:
            msg = conn.recv()
            if msg is None:
                return
            fn, args, has_payload = msg
            payload = conn.recv_bytes() if has_payload else None
        except (EOFError, OSError):
            return
        except MemoryError:  # the payload itself did not fit: say so, the parent decides
            try:
                conn.send(("memory", "", True))
            except OSError:
                return
            continue
        reply = _answer(fn, payload, args)
        del payload
        # What the allocator kept counts against the next task's cap: past a share of it, start afresh.
        retire = _address_space() > RETIRE_SHARE * memory_bytes
        try:
            try:
                conn.send((*reply, retire))
            except MemoryError:
                conn.send(("memory", "", True))
        except OSError:  # the API process is gone (killed mid-task): nobody to answer
            return


class _PlainUnpickler(pickle.Unpickler):
    """Answers of children hold plain data (tuples, dicts, str, bytes, numbers): a child works on hostile bytes,
    so nothing it sends may name a class or function for the API process to call."""

    def find_class(self, module: str, name: str):
        raise pickle.UnpicklingError(f"a child's answer named {module}.{name}; only plain data is accepted")


def _plain_data(raw: bytes):
    return _PlainUnpickler(io.BytesIO(raw)).load()


class _Child:
    """One child process and the parent's end of its pipe."""

    def __init__(self, memory_bytes: int, niceness: int, name: str):
        ctx = multiprocessing.get_context("spawn")
        self.conn, theirs = ctx.Pipe()
        self.proc = ctx.Process(target=serve, args=(theirs, memory_bytes, niceness, os.getpid()), daemon=True,
                                name=name)
        self.proc.start()
        theirs.close()
        self.tasks = 0
        self.retire = False  # the child asked to be replaced

    def run(self, fn: Callable, payload: bytes | None, args: tuple, timeout: float):
        self.tasks += 1
        try:
            self.conn.send((fn, args, payload is not None))
            if payload is not None:
                self.conn.send_bytes(payload)
            if not self.conn.poll(timeout):
                raise ChildFailed("deadline", f"the work did not finish within {timeout:g} s")
            reply = _plain_data(self.conn.recv_bytes())
        except (EOFError, OSError):
            self.proc.join(1)
            raise ChildFailed("crashed", f"the process doing the work died (exit code {self.proc.exitcode})") \
                from None
        except pickle.UnpicklingError as e:
            raise ChildFailed("crashed", str(e)) from None
        kind, self.retire = reply[0], reply[-1]
        if kind == "ok":
            return reply[1]
        if kind == "shape":
            raise ChildShapeError(reply[1], reply[2])
        if kind == "memory":
            raise ChildFailed("memory", "the work needed more memory than a child process may use")
        raise ChildFailed("crashed", reply[1])

    def stop(self) -> None:
        try:
            self.conn.send(None)
        except OSError:
            pass
        self.proc.join(STOP_WAIT_SECONDS)
        self.kill()

    def kill(self) -> None:
        if self.proc.is_alive():
            self.proc.kill()
        self.proc.join(STOP_WAIT_SECONDS)
        self.conn.close()


class CappedPool:
    """``workers`` child processes of at most ``memory_bytes`` of address space each, started on first use.

    :meth:`call` runs ``fn(payload, *args)`` (``fn(*args)`` without a payload) in a free child; ``fn`` must be
    a module-level function (it is sent by name).  A child that dies or runs past its deadline is replaced,
    and only its own task fails.
    """

    def __init__(self, workers: int, memory_bytes: int, tasks_per_child: int = 50, niceness: int = 0,
                 name: str = "fastmesh-child"):
        self.workers, self.memory_bytes, self.tasks_per_child = workers, memory_bytes, tasks_per_child
        self.niceness, self.name = niceness, name
        self._idle: queue.LifoQueue[_Child | None] = queue.LifoQueue()
        for _ in range(workers):
            self._idle.put(None)  # a slot whose child is started when first needed
        self._closed = False
        self.started = 0  # children started, for tests

    def call(self, fn: Callable, payload: bytes | None, *args, timeout: float, wait: float | None = None):
        """``fn``'s return value.

        Raises
        ------
        ChildShapeError
            ``fn`` raised a ShapeError.
        ChildFailed
            Out of memory, past ``timeout`` seconds, died, or (``busy``) no child free within ``wait`` seconds.
        """
        try:
            child = self._idle.get(timeout=wait)
        except queue.Empty:
            raise ChildFailed("busy", f"all {self.workers} processes stayed busy for {wait:g} s") from None
        try:
            if child is None or not child.proc.is_alive():
                child = _Child(self.memory_bytes, self.niceness, f"{self.name}-{self.started}")
                self.started += 1
            return child.run(fn, payload, args, timeout)
        except ChildFailed:
            # Any failure ends the child: one that ran out of memory is whole, but its allocator may keep
            # the cap's worth of pages.
            child.kill()
            child = None
            raise
        finally:
            if child is not None and (child.tasks >= self.tasks_per_child or child.retire or self._closed):
                child.stop()
                child = None
            self._idle.put(child)

    def warm(self) -> None:
        """Start the children now (each takes a second or two to import its libraries, in the background), so
        the first tasks do not wait for that."""
        taken: list[_Child | None] = []
        while len(taken) < self.workers:  # all idle slots at once: the queue is last-in, first-out
            try:
                taken.append(self._idle.get_nowait())
            except queue.Empty:
                break
        try:
            for i, child in enumerate(taken):
                if child is None and not self._closed:
                    taken[i] = _Child(self.memory_bytes, self.niceness, f"{self.name}-{self.started}")
                    self.started += 1
        finally:
            for child in taken:
                self._idle.put(child)

    def pids(self) -> list[int]:
        """The live children's process ids (for tests and benchmarks)."""
        kids = multiprocessing.active_children()
        return [p.pid for p in kids if p.name.startswith(self.name)]

    def close(self) -> None:
        """Stop the idle children; a task under way finishes first and its child stops then."""
        self._closed = True
        idle = []
        while True:
            try:
                idle.append(self._idle.get_nowait())
            except queue.Empty:
                break
        for child in idle:
            if child is not None:
                child.stop()
            self._idle.put(None)
