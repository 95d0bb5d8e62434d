"""Vertex positions fitted to the planes of the input surface around them.

An artist's vertex sits exactly where the surface's planes meet: on the plane of a flat region,
on the line where two planes meet at a crease, at the point where three meet at a corner.  The
decoder gives a cell and the enhancer a position inside it, both a fraction of a cell off.
:func:`fit_to_planes` moves each vertex to the point nearest to the planes of the input samples
around it (the quadric error minimiser of dual contouring), but only along the directions those
planes determine: on a flat region a vertex moves across the plane and not along it, on a
crease onto the crease line, at a corner onto the corner.  A vertex left on a crease may look
farther along it for the corner that ends it.  :func:`distinct` then keeps one vertex of those
the fit put on one point.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .tokenizer.grid import CELL

SPACING_SAMPLES = 4096  # samples whose nearest neighbour gives the median spacing


@dataclass
class FitConfig:
    """Parameters of :func:`fit_to_planes` as the pipeline runs it.

    Attributes
    ----------
    radius : float or None
        Samples within this many 7-bit cells of a vertex take part (Gaussian weights of half
        the radius); None: vertices stay where the enhancer put them.
    rel : float
        A direction counts as determined where its eigenvalue of the planes' quadric is at least
        this share of the largest.
    points : int
        Samples drawn on a mesh input to fit to (a point cloud gives its own points).
    spacings : float
        The radius is at least this many median spacings of the samples: a sparse point cloud
        has few samples within two cells of a vertex.
    reach : float or None
        A vertex on a crease looks this many radii along it for the corner that ends it
        (:func:`fit_to_planes`); None: it does not.
    merge : float or None
        A vertex fitted within this many cells of an earlier one is dropped (:func:`distinct`):
        the decoder often places two vertices near one corner, and the fit puts both on it.
        None: all are kept.
    """

    radius: float | None = 2.0
    rel: float = 0.01
    points: int = 65536
    spacings: float = 3.5
    reach: float | None = 2.0
    merge: float | None = 0.1


def fit_to_planes(vertices: np.ndarray, points: np.ndarray, normals: np.ndarray, radius: float,
                  rel: float = 0.01, tree=None, reach: float | None = None) -> np.ndarray:
    """Move each vertex onto the planes of the samples around it.

    Parameters
    ----------
    vertices : (N, 3) float
    points, normals : (P, 3) float
        Samples of the input surface and their normals (unit; the sign does not matter).
    radius : float
        Samples within this distance of a vertex are its planes; a vertex with fewer than three,
        or whose fitted point lies farther than ``radius`` away, stays where it is.
    rel : float
        Directions whose eigenvalue is below ``rel`` times the largest are left alone.
    tree : scipy.spatial.cKDTree, optional
        Over ``points``, when the caller has one.
    reach : float, optional
        A vertex that lands on a crease (two directions fixed) looks this many times farther
        for the plane that ends the crease, and moves along the crease to the corner where it
        finds one: near a corner each of the three planes holds a quarter of the samples a
        vertex on a flat region sees, and a sparse sample often leaves the corner's last few
        cells empty.  A move that leaves the crease line by more than half of ``radius`` is
        refused (at a thin plate's corner the farther look also sees the plate's other side).

    Returns
    -------
    (N, 3) float64
        The fitted positions.
    """
    from scipy.spatial import cKDTree

    x = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    p = np.asarray(points, dtype=np.float64)
    n = np.asarray(normals, dtype=np.float64)
    tree = tree or cKDTree(p)
    delta, rank, free = _solve(x, p, n, radius, rel, tree)
    out = x + delta
    if reach is not None and (rank == 2).any():
        crease = np.flatnonzero(rank == 2)
        d2, r2, _ = _solve(out[crease], p, n, reach * radius, rel, tree)
        # Only a move along the crease the first fit found: the corner ends this crease.
        along = np.einsum("ni,ni->n", d2, free[crease])[:, None] * free[crease]
        corner = (r2 == 3) & (np.linalg.norm(d2 - along, axis=1) <= radius / 2)
        out[crease[corner]] += d2[corner]
    return out


def _solve(x: np.ndarray, p: np.ndarray, n: np.ndarray, radius: float, rel: float, tree
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The moves (N, 3) of :func:`fit_to_planes` (zero where a vertex stays), the number of
    directions each fixes (N,) (0 where it stays) and its least-fixed direction (N, 3) (unit)."""
    near = tree.query_ball_point(x, radius)
    counts = np.fromiter((len(nb) for nb in near), dtype=np.int64, count=len(x))
    if counts.sum() == 0:
        return np.zeros_like(x), np.zeros(len(x), dtype=np.int64), np.zeros_like(x)
    owner = np.repeat(np.arange(len(x)), counts)
    idx = np.concatenate([np.asarray(nb, dtype=np.int64) for nb in near])
    w = np.exp(-((p[idx] - x[owner]) ** 2).sum(1) / (2 * (radius / 2) ** 2))
    nn = n[idx, :, None] * n[idx, None, :] * w[:, None, None]  # w n n^T per sample
    quad = np.zeros((len(x), 3, 3))
    np.add.at(quad, owner, nn)
    # The residual of each vertex: sum w n n^T (p - x).
    resid = np.zeros((len(x), 3))
    np.add.at(resid, owner, (nn @ (p[idx] - x[owner])[:, :, None])[:, :, 0])
    lam, vec = np.linalg.eigh(quad)  # ascending
    keep = lam > rel * lam[:, -1:]
    inv = np.where(keep, 1.0 / np.where(keep, lam, 1.0), 0.0)
    delta = np.einsum("nij,nj,nkj,nk->ni", vec, inv, vec, resid)  # pseudo-inverse on the kept directions
    ok = (counts >= 3) & (np.linalg.norm(delta, axis=1) <= radius)
    return np.where(ok[:, None], delta, 0.0), np.where(ok, keep.sum(1), 0), vec[:, :, 0]


def fit_samples(shape, unit: np.ndarray, config: FitConfig, seed: int, draw=None) -> tuple[np.ndarray, np.ndarray]:
    """The input samples :func:`fit_to_planes` reads: ``config.points`` drawn on a mesh, a point
    cloud's own points; (P, 3) points in the normalised frame ``unit`` and their normals.  ``draw(n, seed)``
    draws the mesh's samples where given (``request.Frame.samples``: drawn once, shared), else
    ``io.sample_surface``."""
    from .shapes.io import sample_surface

    if shape.faces is None:
        return np.asarray(unit, dtype=np.float64), np.asarray(shape.normals, dtype=np.float64)
    if draw is not None:
        return draw(config.points, seed)
    return sample_surface(shape, config.points, seed=seed, vertices=unit)


def fit_radius(config: FitConfig, points: np.ndarray, tree=None) -> float | None:
    """The radius :func:`fit_to_planes` uses on the samples ``points`` (P, 3) of the normalised frame
    (the unit cube): ``config.radius`` cells, at least ``config.spacings`` median point spacings;
    None when fitting is off."""
    from scipy.spatial import cKDTree

    if config.radius is None:
        return None
    tree = tree or cKDTree(points)
    nn, _ = tree.query(points[:: max(1, len(points) // SPACING_SAMPLES)], k=2)  # a median needs no more
    return max(config.radius * CELL, config.spacings * float(np.median(nn[:, 1])))


def distinct(vertices: np.ndarray, tol: float) -> np.ndarray:
    """Indices (K,) of the vertices (N, 3) kept when each one within ``tol`` of an earlier kept
    one is dropped: the first of each cluster, in order."""
    from scipy.spatial import cKDTree

    x = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    pairs = cKDTree(x).query_pairs(tol, output_type="ndarray")
    if len(pairs) == 0:
        return np.arange(len(x))
    close = [[] for _ in range(len(x))]
    for i, j in pairs:  # i < j
        close[j].append(i)
    kept = np.ones(len(x), dtype=bool)
    for j in range(len(x)):
        if any(kept[i] for i in close[j]):
            kept[j] = False
    return np.flatnonzero(kept)
