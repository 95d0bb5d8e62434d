"""Render docs/pivot.png: one house placed by origin=input, center and bottom, each beside the axes of its
origin, with fastmesh.preview.render.

    python scripts/pivot_picture.py [OUT.png]
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import trimesh

from fastmesh.export.placement import placement
from fastmesh.preview.png import to_png
from fastmesh.preview.render import RenderConfig, render_mesh

PANEL = 3.2  # metres between the panels' origins along X


def house() -> trimesh.Trimesh:
    """A 1 x 0.7 x 0.8 box with a gable roof, standing on y = 0 in a frame of its own far from it."""
    body = trimesh.creation.box(extents=(1.0, 0.7, 0.8))
    body.apply_translation([0, 0.35, 0])
    roof = trimesh.Trimesh([[-0.55, 0.7, -0.45], [0.55, 0.7, -0.45], [0.55, 0.7, 0.45], [-0.55, 0.7, 0.45],
                            [-0.55, 1.1, 0], [0.55, 1.1, 0]],
                           [[0, 1, 5], [0, 5, 4], [2, 3, 4], [2, 4, 5], [1, 2, 5], [0, 4, 3], [0, 3, 2], [0, 2, 1]])
    out = trimesh.util.concatenate([body, roof])
    out.apply_translation([0.9, 0.5, 0.6])  # the input's own frame: the house away from its origin
    return out


def axes(at: np.ndarray, length: float = 1.1, width: float = 0.05) -> trimesh.Trimesh:
    """Three thin rods from ``at`` along +X, +Y and +Z."""
    parts = []
    for k in range(3):
        extents = np.full(3, width)
        extents[k] = length
        rod = trimesh.creation.box(extents=extents)
        shift = np.zeros(3)
        shift[k] = length / 2
        rod.apply_translation(at + shift)
        parts.append(rod)
    return trimesh.util.concatenate(parts)


def main(out: str = "docs/pivot.png") -> None:
    shape = house()
    meshes, origins = [], []
    for k, origin in enumerate(("input", "center", "bottom")):
        at = np.array([k * PANEL, 0.0, 0.0])
        where = placement(shape.vertices, origin)
        meshes += [trimesh.Trimesh(where.apply(shape.vertices) + at, shape.faces), axes(at)]
        origins.append(at)
    scene = trimesh.util.concatenate(meshes)
    # The origins as orange dots drawn over everything (a large depth bias): the centre one lies inside the house.
    cfg = RenderConfig(azimuth_deg=30.0, elevation_deg=15.0, overlay_point_radius=5.0, point_depth_bias=1.0)
    img = render_mesh(scene.vertices, scene.faces, size=900, points=np.array(origins), config=cfg)
    keep = np.flatnonzero(np.any(np.abs(img.astype(int) - img[0, 0].astype(int)).sum(axis=2) > 6, axis=1))
    img = img[max(keep[0] - 8, 0):keep[-1] + 8]  # the rows with something on them
    Path(out).write_bytes(to_png(img, compress_level=9))


if __name__ == "__main__":
    main(*sys.argv[1:])
