"""Faces that pass through each other, and the steps after the solid face stage kept from making any.

The boundary of a solid (``fastmesh.faces.solid``) crosses nothing by construction; a step that moves its vertices
(``pieces.pull_in``) or adds faces it does not check against the rest (``closing.closed_result``'s closure, a
patch taken from the rival) can fold it.  :func:`crossing_faces` finds the faces such a step made cross,
:func:`pull_in_uncrossed` moves a vertex only where no face of it then crosses another, and :func:`adds_crossings`
tells a step's result to refuse.
"""

from __future__ import annotations

import numpy as np

from .meshops import distinct_corners, welded_in_place
from .pieces import pull_in

# Rounds of undoing the moves of vertices whose faces cross after ``pieces.pull_in`` (each round undoes every move
# that made a crossing then; a move undone can only undo crossings, so few rounds are needed).
UNDO_ROUNDS = 8
# Vertices within this share of the longest side are one (as ``meshops.weld``, which the defect count welds by).
WELD_TOL = 1e-6


def crossing_faces(vertices: np.ndarray, faces: np.ndarray, among: np.ndarray | None = None) -> np.ndarray:
    """(F,) bool, the ``faces`` (F, 3) of ``vertices`` (N, 3) that cross a face sharing no vertex with them (after
    welding; ``faces.defects.triangles_cross``, touching within ``defects.TOUCH`` of the longest side not
    counting); with ``among`` (F,) bool, only pairs with at least one face of it are tested."""
    from .defects import PAIR_CHUNK, TOUCH, _candidate_pairs, triangles_cross

    bad = np.zeros(len(faces), dtype=bool)
    if len(faces) < 2:
        return bad
    v, f = welded_in_place(vertices, faces, WELD_TOL)
    tri = v[f]
    pairs = _candidate_pairs(tri)
    # A face welded flat (two corners one) crosses nothing.
    live = distinct_corners(f)
    pairs = pairs[live[pairs].all(1)]
    if among is not None:
        pairs = pairs[np.asarray(among)[pairs].any(1)]
    lo, hi = tri.min(1), tri.max(1)
    tol = TOUCH * (float(np.ptp(v[np.unique(f)], axis=0).max()) or 1.0)
    keep = np.all((lo[pairs[:, 0]] <= hi[pairs[:, 1]] + tol) & (lo[pairs[:, 1]] <= hi[pairs[:, 0]] + tol), axis=1)
    pairs = pairs[keep]
    pairs = pairs[~(f[pairs[:, 0]][:, :, None] == f[pairs[:, 1]][:, None, :]).any(axis=(1, 2))]
    for s in range(0, len(pairs), PAIR_CHUNK):
        p = pairs[s:s + PAIR_CHUNK]
        bad[p[triangles_cross(tri[p[:, 0]], tri[p[:, 1]], tol)].reshape(-1)] = True
    return bad


def adds_crossings(before: tuple[np.ndarray, np.ndarray], after: tuple[np.ndarray, np.ndarray]) -> bool:
    """Whether mesh ``after`` (vertices, faces) has faces crossing each other where ``before`` has fewer."""
    return int(crossing_faces(*after).sum()) > int(crossing_faces(*before).sum())


def pull_in_uncrossed(vertices: np.ndarray, faces: np.ndarray, surface: np.ndarray, limit: float
                      ) -> tuple[np.ndarray, np.ndarray]:
    """``pieces.pull_in`` of a mesh (``vertices`` (N, 3), ``faces`` (F, 3)) that moves no vertex where one of its
    faces would then cross a face it did not cross before: such a move is undone.

    Returns
    -------
    vertices : (N, 3) float64, the connectivity unchanged
    moved : (N,) bool, the vertices moved
    """
    moved_v, moved = pull_in(vertices, surface, limit)
    if not moved.any() or not len(faces):
        return moved_v, moved
    v = np.asarray(vertices, dtype=np.float64)
    crossed = crossing_faces(v, faces)
    for _ in range(UNDO_ROUNDS):
        touched = moved[faces].any(1)
        new = crossing_faces(moved_v, faces, among=touched) & ~crossed & touched
        if not new.any():
            break
        undo = np.zeros(len(v), dtype=bool)
        undo[faces[new].reshape(-1)] = True
        undo &= moved
        moved_v[undo], moved[undo] = v[undo], False
    return moved_v, moved
