"""Units and pivot of a result: where its origin lies, how tall it stands and which axis is up.

The input's Y axis is taken as up (glTF's convention, and what Blender's and most exporters write); with
``input_up`` ``z`` a Z-up input is turned Y-up before anything else (:func:`read_up`, (x, y, z) -> (x, z, -y)), so
the frame below is the turned one.

- ``origin``: ``input`` keeps the input's own frame; ``center`` puts the origin at the centre of the result's
  bounding box; ``bottom`` at the centre of its bottom face (the lowest Y, X and Z centred), where a
  character or a prop stands on the ground.
- ``height``: the result is scaled uniformly so that it is that many metres tall along Y, about its origin
  (the input's origin for ``origin=input``).
- ``up``: ``z`` turns the OBJ and PLY files so the input's up axis becomes +Z ((x, y, z) -> (x, -z, y), as a
  Z-up tool expects); a GLB stays Y-up, as glTF requires.

A result ``v`` in the input's frame is written as ``v * scale + offset`` (then turned for ``up=z``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# (x, y, z) -> (x, -z, y): +Y becomes +Z, a right-handed turn about X.
Z_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])


@dataclass(frozen=True)
class Placement:
    """``v * scale + offset`` maps the result from the input's frame to the written one (Y-up); ``up`` is the
    up axis of the OBJ and PLY files."""

    scale: float = 1.0
    offset: tuple[float, float, float] = (0.0, 0.0, 0.0)
    up: str = "y"

    def apply(self, vertices: np.ndarray) -> np.ndarray:
        """(V, 3) float64 vertices placed (Y-up)."""
        return np.asarray(vertices, dtype=np.float64) * self.scale + np.asarray(self.offset)

    def to_dict(self) -> dict:
        return {"scale": self.scale, "offset": list(self.offset), "up": self.up}


def placement(vertices: np.ndarray, origin: str = "input", height: float | None = None, up: str = "y") -> Placement:
    """The placement of a result with ``vertices`` (V, 3) in the input's frame.

    Raises
    ------
    ValueError
        ``height`` asked of a result with no extent along Y, or an unknown ``origin`` or ``up``.
    """
    if origin not in ("input", "center", "bottom"):
        raise ValueError(f"origin must be input, center or bottom, got {origin!r}")
    if up not in ("y", "z"):
        raise ValueError(f"up must be y or z, got {up!r}")
    v = np.asarray(vertices, dtype=np.float64)
    lo, hi = v.min(axis=0), v.max(axis=0)
    pivot = np.zeros(3)
    if origin == "center":
        pivot = (lo + hi) / 2
    elif origin == "bottom":
        pivot = np.array([(lo[0] + hi[0]) / 2, lo[1], (lo[2] + hi[2]) / 2])
    scale = 1.0
    if height is not None:
        tall = float(hi[1] - lo[1])
        if not tall > 0:
            raise ValueError("height: the result is flat along its up axis (Y), so it cannot be scaled to a height")
        scale = float(height) / tall
    offset = tuple(float(x) + 0.0 for x in -pivot * scale)  # + 0.0 turns -0.0 into 0.0
    return Placement(scale=scale, offset=offset, up=up)


def read_up(vertices: np.ndarray, input_up: str) -> np.ndarray:
    """(V, 3) float64 vertices (or normals) of an input whose up axis is ``input_up``, turned Y-up: the inverse of
    :func:`turn_up`, (x, y, z) -> (x, z, -y) for ``z``."""
    if input_up not in ("y", "z"):
        raise ValueError(f"input_up must be y or z, got {input_up!r}")
    v = np.asarray(vertices, dtype=np.float64)
    return v @ Z_UP if input_up == "z" else v


def turn_up(vertices: np.ndarray, up: str) -> np.ndarray:
    """(V, 3) vertices of a Y-up result as a file with ``up`` as its up axis writes them."""
    v = np.asarray(vertices, dtype=np.float64)
    return v @ Z_UP.T if up == "z" else v
