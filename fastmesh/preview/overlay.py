"""The input drawn beside a result: a few of its points, and those points as the PLY a browser's viewer reads."""

from __future__ import annotations

import numpy as np

from ..shapes.io import sample_triangles
from ..shapes.shape import Shape


def overlay_points(shape: Shape, n: int) -> np.ndarray:
    """Up to ``n`` points of an input shape, (n, 3) float32, input frame: evenly picked points of a cloud,
    area-weighted surface samples of a mesh (its vertices cluster where detail is, not where the surface is)."""
    if shape.faces is None:
        v = shape.vertices
        idx = np.arange(len(v)) if len(v) <= n else np.linspace(0, len(v) - 1, n).astype(np.int64)
        return v[idx].astype(np.float32)
    points, _ = sample_triangles(np.asarray(shape.vertices, np.float64), shape.faces, n, np.random.default_rng(0))
    return points


def points_ply(points: np.ndarray) -> bytes:
    """Binary little-endian PLY of (N, 3) points (float32 x, y, z), the format three.js's PLYLoader reads."""
    p = np.ascontiguousarray(points, dtype="<f4")
    header = (f"ply\nformat binary_little_endian 1.0\ncomment fastmesh input points\nelement vertex {len(p)}\n"
              "property float x\nproperty float y\nproperty float z\nend_header\n")
    return header.encode("ascii") + p.tobytes()
