"""Sheets set apart from the walls they end on, as an artist's panel set into a frame touches the frame without
sharing its edges (``open_planar``'s free mode): every edge keeps at most two faces, and each wall its own corners.
"""

from __future__ import annotations

import numpy as np


def detached(vertices: np.ndarray, faces: np.ndarray, tol: float, length: float) -> tuple[np.ndarray, np.ndarray]:
    """``vertices`` and ``faces`` with each sheet that ends on a wall set apart from it, as an artist's panel set into
    a frame touches the frame without sharing its edges: the sheet's faces around each end of such an edge take a
    vertex of their own at the same place, and the wall's vertices there go where they lie on a straight edge
    (:func:`_straightened`).  A sheet ends on a wall along an edge of three faces two of which share a plane (the
    wall's triangulation runs a diagonal along it) or along an open edge at least ``length`` long that lies on faces
    of other planes (within ``tol``, at a quarter, half and three quarters of it: not a sliver between two corners
    a rounding apart).  An edge of three faces none of which share a plane is left: the check after refuses the
    surface."""
    n = np.cross(vertices[faces[:, 1]] - vertices[faces[:, 0]], vertices[faces[:, 2]] - vertices[faces[:, 0]])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    offset = np.einsum("ij,ij->i", n, vertices[faces[:, 0]])
    e = np.sort(np.c_[faces.ravel(), faces[:, [1, 2, 0]].ravel()], axis=1)
    edges, inverse, count = np.unique(e, axis=0, return_inverse=True, return_counts=True)
    ends = {}  # (vertex, a face of the sheet that ends there): a face of the wall
    for j in np.nonzero(count != 2)[0]:
        own = np.nonzero(inverse.ravel() == j)[0] // 3
        if count[j] == 1:
            sheet, (a, b) = int(own[0]), vertices[edges[j]]
            on = [_on_faces(vertices, faces, n, offset, a + t * (b - a), tol) & (n @ n[sheet] < 1 - 1e-6)
                  for t in (0.25, 0.5, 0.75)]
            if np.linalg.norm(b - a) < length or not all(x.any() for x in on):
                continue
            wall = int(on[1].argmax())
        else:
            pair = [(i, k) for i, k in ((0, 1), (0, 2), (1, 2)) if len(own) == 3 and n[own[i]] @ n[own[k]] > 1 - 1e-6]
            if not pair:
                continue
            sheet, wall = int(own[3 - sum(pair[0])]), int(own[pair[0][0]])
        ends |= {(int(v), sheet): wall for v in edges[j]}
    out, faces = list(vertices), faces.copy()
    for (v, sheet), wall in sorted(ends.items()):
        fan = _fan(faces, v, sheet, (np.abs(n @ n[wall]) > 1 - 1e-6) & (np.abs(offset - offset[wall]) < tol))
        if fan.any():
            faces[fan] = np.where(faces[fan] == v, len(out), faces[fan])
            out.append(out[v])
    faces = _straightened(np.array(out), faces, sorted({v for v, _ in ends}))
    used = np.unique(faces)
    return np.array(out)[used], np.searchsorted(used, faces)


def _fan(faces: np.ndarray, v: int, sheet: int, wall: np.ndarray) -> np.ndarray:
    """(F,) the faces about vertex ``v`` that the sheet holding face ``sheet`` makes there: those reached from it
    across edges at ``v`` that two faces share, none of them on the wall (``wall`` (F,): the faces in its plane).
    A sheet folded a few degrees (a low-poly quad whose corners are not in one plane) is one sheet."""
    around = (faces == v).any(1)
    ring = np.nonzero(around & ~wall)[0]
    count = {}
    for i in np.nonzero(around)[0]:
        for w in faces[i]:
            count[int(w)] = count.get(int(w), 0) + (w != v)
    reached, todo = {sheet}, [sheet]
    while todo:
        i = todo.pop()
        for j in ring:
            shared = set(faces[i].tolist()) & set(faces[j].tolist()) - {v}
            if j not in reached and len(shared) == 1 and count[shared.pop()] == 2:
                reached.add(int(j))
                todo.append(int(j))
    out = np.zeros(len(faces), dtype=bool)
    out[list(reached)] = True
    return out


def _on_faces(vertices: np.ndarray, faces: np.ndarray, n: np.ndarray, offset: np.ndarray, point: np.ndarray,
              tol: float) -> np.ndarray:
    """(F,) whether ``point`` (3,) lies on each face (within ``tol`` of its plane, inside or on its edges); ``n`` and
    ``offset`` the faces' unit normals and offsets."""
    near = np.abs(n @ point - offset) < tol
    corners = vertices[faces]  # (F, 3, 3)
    inside = np.ones(len(faces), dtype=bool)
    for k in range(3):
        side = np.cross(corners[:, (k + 1) % 3] - corners[:, k], point - corners[:, k])
        inside &= np.einsum("ij,ij->i", side, n) >= -tol * np.linalg.norm(corners[:, (k + 1) % 3] - corners[:, k],
                                                                           axis=1)
    return near & inside


def _straightened(vertices: np.ndarray, faces: np.ndarray, ids: list[int]) -> np.ndarray:
    """``faces`` with each vertex of ``ids`` that lies on a straight edge of its faces (between two of its neighbours,
    along an open border or where two walls meet) moved onto one of those neighbours, where no face it keeps turns
    over or loses its area: a wall a sheet ended on has its corners only, as before the sheet cut it."""
    for v in ids:
        ring = (faces == v).any(1)
        others = np.setdiff1d(faces[ring], [v])
        d = vertices[others] - vertices[v]
        unit = d / np.linalg.norm(d, axis=1, keepdims=True)
        cos = unit @ unit.T
        for a in others[(cos < -1 + 1e-9).any(1)]:  # a neighbour with another straight across v
            moved = np.where(faces[ring] == v, a, faces[ring])
            kept = (moved != np.roll(moved, 1, axis=1)).all(1)
            old = np.cross(*(vertices[faces[ring][:, k]] - vertices[faces[ring][:, 0]] for k in (1, 2)))
            new = np.cross(*(vertices[moved[:, k]] - vertices[moved[:, 0]] for k in (1, 2)))
            area = np.linalg.norm(new, axis=1)
            if ((np.einsum("ij,ij->i", old, new) > 0) & (area > 1e-9 * area.max()))[kept].all():
                faces = np.vstack([faces[~ring], moved[kept]])
                break
    return faces
