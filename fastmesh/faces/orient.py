"""Consistent, outward windings: each face's flip fixed along a spanning forest of the face graph
(``shapes.windings``); open pieces turned to face the input (:func:`face_input`); a mesh's pieces stored inside out
turned (:func:`outward_pieces`)."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from ..shapes.windings import face_pairs, winding_flips
from .meshops import open_sides, piece_labels, side_counts

# A face's side is read from this many input samples nearest its centroid (:func:`sides_asked`)...
SIDE_SAMPLES = 8
# ... each of which says it where its normal lies within acos(this) of the face's normal, either way.
SIDE_COS = 0.3
# A piece with an open edge is a sheet, sided by the input rather than by its signed volume, where that volume is
# under this share of its area^(3/2): random wavy sheets read 0.0000, the open results of held-out inputs 0.005 to
# 0.06 (a sphere's whole surface 0.094), which their signed volume sides rightly.
SHEET_VOLUME = 0.002


def orient_faces(vertices: np.ndarray, faces: np.ndarray, outward: bool = True) -> np.ndarray:
    """Consistent winding across edges shared by exactly two faces, then each part outward.

    A spanning forest of the face graph fixes each face's flip relative to its part's root
    (``shapes.windings.winding_flips``; edges with more than two faces do not constrain
    winding).  With ``outward``, a part whose signed
    volume about the vertex centroid is negative is flipped (exact for closed parts, a
    heuristic for open ones).

    Returns
    -------
    (F, 3) int64 faces, same order, some reversed.
    """
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3).copy()
    if len(f) == 0:
        return f
    flip, label = winding_flips(*face_pairs(f, len(vertices)), len(f))
    f[flip] = f[flip][:, ::-1]
    if outward:
        v = np.asarray(vertices, dtype=np.float64)
        inv = _volumes(v, f, label, v[np.unique(f)].mean(0))[label] < 0
        f[inv] = f[inv][:, ::-1]
    return f


def outward_pieces(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """``faces`` with each piece wound one way whose signed volume about its centroid is negative reversed: a mesh
    stored inside out (as many game formats keep theirs) shows a renderer the backs of its faces.  Exact for a
    closed piece, and read as :func:`orient_faces` reads it for an open one that encloses a volume (a body open at
    the neck); a sheet (``SHEET_VOLUME``) and a piece with an edge in three faces or two faces wound against each
    other stay as they are: their side is not theirs to tell.  A closed piece inside another (a cavity, which no
    renderer shows) is turned outward too, as :func:`orient_faces` turns it.

    Parameters
    ----------
    vertices : (V, 3) float
    faces : (F, 3) int

    Returns
    -------
    (F, 3) int64 faces, same order, the turned pieces' reversed
    """
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3).copy()
    if len(f) == 0:
        return f
    v = np.asarray(vertices, dtype=np.float64)
    fa, _, same_dir = face_pairs(f, len(v))
    label = piece_labels(f)
    tri = v[f]
    area_normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    count = side_counts(f)
    volume = _volumes(v, f, label, _centres(v, f, label)[label])
    keep = _sheets(label, area_normal, volume, count == 1)
    keep[label[fa[same_dir]]] = True
    keep[np.tile(label, 3)[count > 2]] = True
    turn = (~keep & (volume < 0))[label]
    f[turn] = f[turn][:, ::-1]
    return f


def face_input(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """``faces`` with each sheet turned where its area faces against the input more than with it: a piece with an
    open edge that encloses almost no volume (``SHEET_VOLUME``: a roof, a terrain, a wall) has no inside for
    :func:`orient_faces`'s signed volume to find, and its side is the input's to tell.  Closed pieces, and open
    ones the signed volume can read (a pose open at the neck), stay as they are.

    Parameters
    ----------
    vertices : (V, 3) float
    faces : (F, 3) int, wound alike within each piece (:func:`orient_faces`)
    points : (P, 3) float, samples of the input surface, in the frame of ``vertices``
    normals : (P, 3) float, their unit normals, pointing out of the input

    Returns
    -------
    (F, 3) int64 faces, same order, the turned pieces' reversed
    """
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3).copy()
    if len(f) == 0 or len(points) == 0:
        return f
    v = np.asarray(vertices, dtype=np.float64)
    tri = v[f]
    area_normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # twice the area along the normal
    label = piece_labels(f)
    n = label.max() + 1
    nearest = cKDTree(np.asarray(points, dtype=np.float64)).query(tri.mean(1))[1]
    vote = np.bincount(label, np.einsum("fd,fd->f", area_normal, np.asarray(normals)[nearest]), n)
    volume = _volumes(v, f, label, _centres(v, f, label)[label])
    return np.where(((vote < 0) & _sheets(label, area_normal, volume, open_sides(f)))[label][:, None], f[:, ::-1], f)


def _sheets(label: np.ndarray, area_normal: np.ndarray, volume: np.ndarray, open_side: np.ndarray) -> np.ndarray:
    """(pieces,) bool: the pieces (faces labelled ``label`` (F,), twice their areas along their normals
    ``area_normal`` (F, 3)) with an open edge (``open_side`` (3F,), per side of ``meshops.face_sides``) whose signed
    volume about their vertices' centroid (``volume`` (pieces,)) is under ``SHEET_VOLUME`` times their area to the
    power 3/2."""
    n = label.max() + 1
    open_piece = np.zeros(n, dtype=bool)
    open_piece[np.tile(label, 3)[open_side]] = True
    area = np.bincount(label, np.linalg.norm(area_normal, axis=1), n) / 2
    return open_piece & (np.abs(volume) < SHEET_VOLUME * area**1.5)


def _centres(v: np.ndarray, f: np.ndarray, label: np.ndarray) -> np.ndarray:
    """(pieces, 3) the mean of each piece's face corners (faces ``f`` (F, 3) labelled ``label`` (F,))."""
    n = label.max() + 1
    centre = np.zeros((n, 3))
    corner = np.repeat(label, 3)
    np.add.at(centre, corner, v[f].reshape(-1, 3))
    return centre / np.maximum(np.bincount(corner, minlength=n), 1)[:, None]


def _volumes(v: np.ndarray, f: np.ndarray, label: np.ndarray, about: np.ndarray) -> np.ndarray:
    """(pieces,) the signed volume of each piece (faces ``f`` (F, 3) labelled ``label`` (F,)) about ``about``: one
    point (3,) for all, or one per face (F, 3); exact for a closed piece wherever the point, an open piece's
    depends on it."""
    t = v[f] - (about if np.ndim(about) == 1 else about[:, None])
    return np.bincount(label, np.einsum("ij,ij->i", t[:, 0], np.cross(t[:, 1], t[:, 2])), label.max() + 1) / 6


def sides_asked(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """(F,) int8 the side the input asks of each of ``faces`` (F, 3) as wound: 0 where the ``SIDE_SAMPLES`` input
    samples (``points``, ``normals`` (P, 3)) nearest its centroid all face along its normal, 1 where all face
    against it, -1 where they disagree or lie across it (both sides of a part thinner than their spread, a crease).
    Normals that all point into the input (Quake's formats) turn every side: which faces ask alike does not
    change."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if len(f) == 0 or len(points) == 0:
        return np.full(len(f), -1, dtype=np.int8)
    t = v[f]
    n = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    _, idx = cKDTree(np.asarray(points, dtype=np.float64)).query(t.mean(1), k=min(SIDE_SAMPLES, len(points)))
    dots = np.einsum("fkd,fd->fk", np.asarray(normals, dtype=np.float64)[idx.reshape(len(f), -1)], n)
    return np.where((dots > SIDE_COS).all(1), 0, np.where((dots < -SIDE_COS).all(1), 1, -1)).astype(np.int8)

