"""The shape every step reads: :class:`Shape` (a mesh or a point cloud in its own frame), the reversible map
into the unit cube (:class:`Normalization`), the formats and limits of loading, and :class:`ShapeError`."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from .errors import ShapeError

if TYPE_CHECKING:
    from .texture import SurfaceTexture

MESH_FORMATS = ("obj", "glb", "gltf", "ply", "stl", "off")
POINT_FORMATS = ("xyz", "txt", "npy", "npz")  # plus ply without faces
SUPPORTED_FORMATS = MESH_FORMATS + tuple(f for f in POINT_FORMATS if f not in MESH_FORMATS)
EXPORT_FORMATS = ("glb", "obj", "ply")

# Default limits; the service narrows them through its settings.
MAX_POINTS = 2_000_000
MAX_FACES = 2_000_000
# Smallest bounding-box side: 1 / MIN_EXTENT is still a normal float64 (subnormal extents overflow the scale).
MIN_EXTENT = float(np.finfo(np.float64).tiny)


@dataclass
class Shape:
    """A mesh or a point cloud in its original frame.

    Attributes
    ----------
    vertices : (N, 3) float64
        Vertex (or point) positions, input units.
    faces : (F, 3) int64 or None
        Triangles for a mesh, None for a point cloud.
    normals : (N, 3) float64 or None
        Unit normals of a point cloud (given or estimated); None for a mesh.
    texture : fastmesh.shapes.texture.SurfaceTexture or None
        The base-colour texture of a textured glTF mesh, when loaded with ``texture=True``.
    """

    vertices: np.ndarray
    faces: np.ndarray | None = None
    normals: np.ndarray | None = None
    texture: SurfaceTexture | None = None

    @property
    def kind(self) -> str:
        return "mesh" if self.faces is not None else "points"

    @property
    def bounds(self) -> np.ndarray:
        return np.stack([self.vertices.min(0), self.vertices.max(0)])


@dataclass(frozen=True)
class Normalization:
    """Map ``v -> (v - center) * scale`` into [-0.5, 0.5]^3 and back.

    The longest bounding-box side becomes 1, the box centre the origin; the other
    sides keep their proportions (uniform scale, so angles survive).
    """

    center: np.ndarray  # (3,)
    scale: float

    @classmethod
    def fit(cls, points: np.ndarray) -> Normalization:
        """Raises :class:`ShapeError` for a zero extent, and for one the unit cube cannot hold in float64
        (wider than the largest float, or so small that its inverse overflows)."""
        lo, hi = np.asarray(points, dtype=np.float64).min(0), np.asarray(points, dtype=np.float64).max(0)
        with np.errstate(over="ignore"):
            extent = float((hi - lo).max())
        if extent == 0:
            raise ShapeError("degenerate", "shape has zero extent (all points coincide)")
        if not np.isfinite(extent):
            raise ShapeError("out_of_range", "coordinates span more than the largest float64 number "
                                             "(about 1.8e308); scale the shape down")
        if extent < MIN_EXTENT:
            raise ShapeError("degenerate", f"the shape is {extent:.3g} units across, too small to be scaled to "
                                           f"the unit cube (at least {MIN_EXTENT:.3g}); scale it up")
        return cls(center=lo / 2.0 + hi / 2.0, scale=1.0 / extent)

    def apply(self, v: np.ndarray) -> np.ndarray:
        return (np.asarray(v, dtype=np.float64) - self.center) * self.scale

    def invert(self, v: np.ndarray) -> np.ndarray:
        return np.asarray(v, dtype=np.float64) / self.scale + self.center

    def to_dict(self) -> dict:
        return {"center": [float(c) for c in self.center], "scale": float(self.scale)}


def too_many(n: int, limit: int, what: str = "points/vertices") -> ShapeError:
    return ShapeError("too_large", f"{n} {what} exceed the limit of {limit}")
