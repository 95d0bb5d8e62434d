"""An upload parsed into the compact stored input, as a capped child process does it (:mod:`service.children`).

This module imports no web framework: it is what a child imports.
"""

from __future__ import annotations

from fastmesh.shapes.io import load_shape
from fastmesh.shapes.shape import Shape


def input_info(filename: str, shape: Shape) -> dict:
    """The ``input`` facts of a job: its file name, kind and counts."""
    if shape.faces is None:
        return {"filename": filename, "kind": "points", "points": int(len(shape.vertices)),
                "vertices": None, "faces": None}
    return {"filename": filename, "kind": "mesh", "points": None, "vertices": int(len(shape.vertices)),
            "faces": int(len(shape.faces))}


def parse_upload(data: bytes, filename: str, max_points: int, max_faces: int, texture: bool = False
                 ) -> tuple[dict, bytes]:
    """``(input facts, stored input bytes)`` of an upload; raises :class:`fastmesh.shapes.shape.ShapeError`.

    A point cloud's normals are left as the file gives them: estimating them takes seconds for a large
    cloud and is the worker's.  ``texture``: keep a glTF's base-colour texture (``bake``).
    """
    from fastmesh_jobs.blobs import shape_to_bytes

    shape = load_shape(data, filename=filename, max_points=max_points, max_faces=max_faces, normals=False,
                       texture=texture)
    del data
    return input_info(filename, shape), shape_to_bytes(shape)
