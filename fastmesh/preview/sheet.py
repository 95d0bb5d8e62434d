"""A contact sheet of meshes side by side: one row per mesh, shaded from the front and the back 3/4 views with
the back of every face marked, then the front view as a wireframe.  ``fastmesh eval --sheets`` writes one per
shape (reference, ours, the classical anchor)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from .raster import DEFAULT_CONFIG, RenderConfig
from .render import render_mesh

BACK_COLOR = (0.9, 0.12, 0.1)  # faces seen from their back: red, as modelling tools mark them
GAP = 4  # pixels between panels
GAP_COLOR = 255  # white rules between panels
MISSING_COLOR = (200, 200, 200)  # a panel whose mesh failed or is empty


def sheet_columns(config: RenderConfig = DEFAULT_CONFIG) -> list[tuple[RenderConfig, bool]]:
    """The panels of a row: (look, wireframe) for the front 3/4 view, the back 3/4 view from below and the
    front view's wireframe."""
    back = replace(config, azimuth_deg=config.azimuth_deg + 180.0, elevation_deg=-config.elevation_deg)
    return [(config, False), (back, False), (config, True)]


def contact_sheet(meshes: list[tuple[np.ndarray, np.ndarray] | None], size: int = 256,
                  config: RenderConfig = DEFAULT_CONFIG) -> np.ndarray:
    """One row per mesh of :func:`sheet_columns` panels, each ``size`` pixels a side.

    Parameters
    ----------
    meshes : list of (vertices (V, 3) float, faces (F, 3) int), or None for a mesh that failed
    size : int, the side of each panel
    config : RenderConfig, the front view's look

    Returns
    -------
    (rows * (size + GAP) - GAP, 3 * (size + GAP) - GAP, 3) uint8
    """
    cols = sheet_columns(config)
    rows = []
    for mesh in meshes:
        panels = []
        for look, wire in cols:
            if mesh is None or len(mesh[1]) == 0:
                panels.append(np.broadcast_to(np.asarray(MISSING_COLOR, np.uint8), (size, size, 3)))
            else:
                panels.append(render_mesh(mesh[0], mesh[1], size=size, wireframe=wire, config=look,
                                          back_color=BACK_COLOR))
        rows.append(_join(panels, axis=1))
    return _join(rows, axis=0)


def _join(images: list[np.ndarray], axis: int) -> np.ndarray:
    """Images (H, W, 3) joined along ``axis`` with ``GAP`` white pixels between them."""
    out = [images[0]]
    for im in images[1:]:
        shape = list(im.shape)
        shape[axis] = GAP
        out += [np.full(shape, GAP_COLOR, dtype=np.uint8), im]
    return np.concatenate(out, axis=axis)
