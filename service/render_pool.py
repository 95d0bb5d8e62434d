"""Previews and input overlays made in capped child processes (:class:`service.children.CappedPool`).

A preview of a dense input decodes tens of MB and rasterises it, and an ``input.ply`` samples the
stored input's surface; done in the API process, a burst of them would grow it by gigabytes and the
allocator would keep much of that.  Here each runs in one of a few low-priority children with a
memory cap, and the API holds only the stored bytes going in and the PNG or PLY coming out.  This
module imports no web framework: it is what a child imports.
"""

from __future__ import annotations

from .children import CappedPool

TASKS_PER_CHILD = 50  # a child is replaced after this many renders: what its allocator kept goes with it
RENDER_NICENESS = 10  # renders yield the CPU to the API process, so status polls stay fast during a burst
DEFAULT_MEMORY_BYTES = 1536 * 1024 * 1024


def render_blob(blob: bytes, of: str, size: int, wireframe: bool) -> bytes:
    """PNG bytes of a stored result (``of == "result"``: npz of vertices and faces) or input (a Shape's npz).

    A result without faces (a degenerate generation) is drawn as its vertices, so the preview still
    shows what came out.  Raises :class:`fastmesh.shapes.shape.ShapeError` when there is nothing drawable.
    """
    from fastmesh.preview.render import render_mesh, render_points, render_shape, to_png
    from fastmesh_jobs.blobs import mesh_from_bytes, shape_from_bytes

    if of == "result":
        vertices, faces = mesh_from_bytes(blob)
        img = render_mesh(vertices, faces, size=size, wireframe=wireframe) if len(faces) else \
            render_points(vertices, size=size)
    else:
        shape = shape_from_bytes(blob)
        img = render_shape(shape, size=size, wireframe=wireframe and shape.faces is not None)
    return to_png(img)


def overlay_blob(blob: bytes, n: int) -> bytes:
    """``input.ply``: up to ``n`` points of a stored input (a Shape's npz) as a binary PLY."""
    from fastmesh.preview.overlay import overlay_points, points_ply
    from fastmesh_jobs.blobs import shape_from_bytes

    return points_ply(overlay_points(shape_from_bytes(blob), n))


class RenderPool:
    """``workers`` render processes of at most ``memory_bytes`` each, started on first use; :meth:`close`
    stops them.  A render that fails raises what :meth:`service.children.CappedPool.call` raises."""

    def __init__(self, workers: int, memory_bytes: int = DEFAULT_MEMORY_BYTES):
        self.pool = CappedPool(workers, memory_bytes, TASKS_PER_CHILD, RENDER_NICENESS, name="fastmesh-render")

    def render(self, of: str, blob: bytes, size: int, wireframe: bool, timeout: float) -> bytes:
        return self.pool.call(render_blob, blob, of, size, wireframe, timeout=timeout)

    def overlay(self, blob: bytes, n: int, timeout: float) -> bytes:
        return self.pool.call(overlay_blob, blob, n, timeout=timeout)

    def warm(self) -> None:
        """Start the render processes now, in the background (see :meth:`CappedPool.warm`)."""
        self.pool.warm()

    def close(self) -> None:
        self.pool.close()
