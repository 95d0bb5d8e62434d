"""Curved regions given the faces their curvature needs: edges split where the input bends away from them.

The decoder places about as many vertices on a curved car body as on a box of the same size, so a curved region
comes back as a few long flat faces cut across its curve (a TORCS car at a fifth of its artist's faces).
:func:`refine` splits, in rounds, each edge whose middle lies farther than ``tol`` from the input surface at the
nearest point of that surface, as read from the tangent planes of the input samples around the middle that face
the way the edge's faces do (so a thin part's other side is never taken for its own), where those samples' normals
spread (the input bends there).  Flat regions, straight creases and the faces of a flat-faced shape are left as
they are.  A split whose faces would then cross another face or turn over keeps its new vertex at the edge's middle
(a flat split: no shape added, none folded), so a surface free of crossings stays free of them; every split keeps
the faces' winding, a closed surface closed and an edge-manifold one edge-manifold.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from .crossings import crossing_faces
from .facecount import MAX_MOVE, project, side_edges, split_sides
from .meshops import face_normals

# Input samples read around an edge's middle; those facing within FACING_COS of the edge's faces give its point
# on the surface (a sample whose normal turns further is the far side of a thin part or across a crease).
AROUND = 8
FACING_COS = 0.5
# Splitting rounds: each splits an edge at most once per face, so a face becomes at most 2 ** ROUNDS faces.
ROUNDS = 3
# Only where the input bends is an edge split: where the normals of the samples read there spread by more than
# about this many degrees (their mean shorter than its cosine).  A flat region the decoder left lumpy is the
# vertices' fault, not too few faces: splits there double its faces and leave the lumps.
BEND_DEGREES = 3.0


def edge_normals(vertices: np.ndarray, faces: np.ndarray, which: np.ndarray, n_edges: int) -> np.ndarray:
    """(E, 3) unit normals of the edges: the sum of the area-weighted normals of the faces on each (``which``
    (3F,) the edge of each face side, as ``facecount.side_edges`` gives it)."""
    out = np.zeros((n_edges, 3))
    np.add.at(out, which, np.tile(face_normals(vertices, faces), (3, 1)))
    return out / np.maximum(np.linalg.norm(out, axis=1, keepdims=True), 1e-300)


def _chosen(deviation: np.ndarray, which: np.ndarray, third: np.ndarray, n_faces: int, tol: float) -> np.ndarray:
    """(S,) edges to split in one round: each deviating more than ``tol``, farthest first, no two in one face,
    none whose faces face one corner (a face twice, or a pillow of two: splitting it would give an edge of
    three or four faces)."""
    sides_of = np.bincount(which, minlength=len(deviation))
    order = np.argsort(which, kind="stable")
    start = np.concatenate([[0], np.cumsum(sides_of)])
    taken = np.zeros(n_faces, dtype=bool)
    chosen = []
    for e in np.argsort(-deviation, kind="stable"):
        if deviation[e] <= tol:
            break
        sides = order[start[e]:start[e + 1]]
        around = sides % n_faces
        if taken[around].any() or len(np.unique(third[sides])) < len(sides):
            continue
        taken[around] = True
        chosen.append(e)
    return np.asarray(chosen, dtype=np.int64)


def refine(vertices: np.ndarray, faces: np.ndarray, samples: np.ndarray, normals: np.ndarray, tol: float,
           rounds: int = ROUNDS) -> tuple[np.ndarray, np.ndarray, int]:
    """Split the edges whose middles lie farther than ``tol`` from the input surface, at that surface.

    Parameters
    ----------
    vertices : (N, 3) float
    faces : (F, 3) int, wound outward (or towards the input's normals where open)
    samples, normals : (P, 3) float, the input's samples and their unit normals, pointing out of what they enclose
    tol : float, in the unit of the positions
    rounds : int

    Returns
    -------
    vertices : (N + S, 3) float64, the first N unchanged
    faces : (F + 2S', 3) int64, windings kept
    splits : int, S
    """
    v = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    tree, pts, nrm = cKDTree(samples), np.asarray(samples, np.float64), np.asarray(normals, np.float64)
    total = 0
    for _ in range(rounds):
        if len(f) == 0:
            break
        edges, which = side_edges(f)
        lengths = np.linalg.norm(v[edges[:, 1]] - v[edges[:, 0]], axis=1)
        middle = 0.5 * (v[edges[:, 0]] + v[edges[:, 1]])
        onto, mean = project(middle, tree, pts, nrm, MAX_MOVE * lengths, AROUND, edge_normals(v, f, which, len(edges)),
                             FACING_COS)
        dev = np.linalg.norm(onto - middle, axis=1)
        dev[mean > np.cos(np.radians(BEND_DEGREES))] = 0.0  # the input is flat there
        chosen = _chosen(dev, which, f[:, [2, 0, 1]].T.reshape(-1), len(f), tol)
        if len(chosen) == 0:
            break
        index = np.full(len(edges), -1, dtype=np.int64)
        index[chosen] = len(v) + np.arange(len(chosen))
        split, made = split_sides(f, which, index)
        placed = _placed_unfolded(np.concatenate([v, onto[chosen]]), split, made, len(v), middle[chosen])
        if placed is None:
            break  # a face made crosses even split flat: the round is not made
        v, f = placed, split
        total += len(chosen)
    return v, f, total


def _placed_unfolded(vertices: np.ndarray, faces: np.ndarray, made: np.ndarray, first: int,
                     middles: np.ndarray) -> np.ndarray | None:
    """``vertices`` with each new one (from index ``first``; ``middles`` (S, 3) their edges' middles) whose faces
    (among those ``made`` (F,) bool) turn over (face against the face they split) or cross another face put back
    at its edge's middle, until none do; None where a face made still crosses one with every vertex of it back
    (a face split at the middle lies in its parent's plane, yet one touching another face within the crossing
    test's tolerance may have a half that does not)."""
    v = vertices.copy()
    flat_v = vertices.copy()
    flat_v[first:] = middles
    flat = np.zeros(len(middles), dtype=bool)
    for _ in range(len(middles) + 1):
        turned = (face_normals(v, faces) * face_normals(flat_v, faces)).sum(1) < 0
        bad = crossing_faces(v, faces, among=made) | turned
        new = faces[bad & made]
        new = np.unique(new[new >= first]) - first
        new = new[~flat[new]]
        if len(new) == 0:
            return None if (bad & made).any() else v
        flat[new] = True
        v[first + new] = middles[new]
    return v

