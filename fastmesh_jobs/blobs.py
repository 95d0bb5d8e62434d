"""A job's binary data in Redis: its parsed input, its results and its previews, and the npz they are stored as.

Keys (``P`` is ``Settings.redis_prefix``)::

    P:input:<id>            npz bytes of the parsed input shape (:func:`shape_to_bytes`)
    P:result:<id>:<fmt>     exported mesh (glb/obj/ply) and ``npz`` (vertices, faces) for other formats
    P:preview:<id>          hash of the job's rendered previews (``service.preview``)

They expire with the job: :meth:`fastmesh_jobs.states.JobStates.finish` sets the retention clock on them too.
"""

from __future__ import annotations

import io

import numpy as np

from fastmesh.shapes.shape import EXPORT_FORMATS, Normalization, Shape
from fastmesh.shapes.texture import SurfaceTexture

from .part import StorePart


def _exact(values: np.ndarray) -> np.ndarray:
    """``values`` as float32 where that holds every value exactly (most mesh files store float32), else float64."""
    values = np.asarray(values, np.float64)
    small = values.astype(np.float32)
    return small if np.array_equal(small.astype(np.float64), values) else values


def shape_to_bytes(shape: Shape) -> bytes:
    """The parsed input, as it travels to the worker and sits in Redis for the job's retention (npz, no pickle).

    Lossless, so a job gives the result the CLI and the Python API give for the same file and parameters
    (a change of 1e-8 in a coordinate can change which vertices the decoder samples): positions and normals
    are float32 where the file's numbers are float32 (12 bytes a point), float64 otherwise; faces int32.
    """
    arrays = {"vertices": _exact(shape.vertices)}
    if shape.faces is not None:
        arrays["faces"] = np.asarray(shape.faces, np.int32 if len(shape.vertices) < 2**31 else np.int64)
    if shape.normals is not None:
        arrays["normals"] = _exact(shape.normals)
    if shape.texture is not None:
        arrays.update(shape.texture.to_arrays())
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


def shape_from_bytes(data: bytes) -> Shape:
    """The shape :func:`shape_to_bytes` stored (float64 positions and normals, int64 faces); also reads the
    unit-cube layout (``unit``, ``center``, ``scale``) of inputs stored by earlier versions."""
    with np.load(io.BytesIO(data), allow_pickle=False) as z:
        if "unit" in z:
            vertices = Normalization(center=z["center"], scale=float(z["scale"])).invert(z["unit"])
        else:
            vertices = z["vertices"].astype(np.float64)
        return Shape(vertices=vertices, faces=z["faces"].astype(np.int64) if "faces" in z else None,
                     normals=z["normals"].astype(np.float64) if "normals" in z else None,
                     texture=SurfaceTexture.from_arrays(z))


def mesh_to_bytes(vertices: np.ndarray, faces: np.ndarray) -> bytes:
    """A result mesh as the ``npz`` result: ``vertices`` (V, 3) float64 and ``faces`` (F, 3) int64."""
    buf = io.BytesIO()
    np.savez(buf, vertices=np.asarray(vertices, np.float64), faces=np.asarray(faces, np.int64))
    return buf.getvalue()


def mesh_from_bytes(data: bytes) -> tuple[np.ndarray, np.ndarray]:
    """``(vertices (V, 3), faces (F, 3))`` of a result :func:`mesh_to_bytes` stored."""
    with np.load(io.BytesIO(data), allow_pickle=False) as z:
        return z["vertices"], z["faces"]


class Blobs(StorePart):
    """A job's input, results and previews: the keys they live under and their reads and writes."""

    def k_input(self, job_id: str) -> str:
        return f"{self.prefix}:input:{job_id}"

    def k_result(self, job_id: str, fmt: str) -> str:
        return f"{self.prefix}:result:{job_id}:{fmt}"

    def k_preview(self, job_id: str) -> str:
        """Hash of the job's rendered previews (``service.preview``)."""
        return f"{self.prefix}:preview:{job_id}"

    def result_keys(self, job_id: str) -> list[str]:
        return [self.k_result(job_id, f) for f in (*EXPORT_FORMATS, "npz")]

    def put_result(self, job_id: str, fmt: str, data: bytes, ttl: int | None = None) -> None:
        self.redis.set(self.k_result(job_id, fmt), data, ex=ttl or self.settings.retention_seconds)

    def get_result(self, job_id: str, fmt: str) -> bytes | None:
        return self.redis.get(self.k_result(job_id, fmt))

    def get_input(self, job_id: str) -> bytes | None:
        return self.redis.get(self.k_input(job_id))
