"""Varied inputs for the device check (``tests/test_gpu.py``, ``benchmarks/gpu_check.py``), made here from seeds.

Point clouds of smooth analytic surfaces (ellipsoids, tori, wavy spheres, superellipsoids: no plane to rebuild
them from, so the vertex decoder runs) at varied sizes, point counts, noise, poses and units; meshes of the same
surfaces and of posed primitives (``fastmesh.evaluation.primitives``: a flat-faced one is rebuilt from its planes);
and the artist meshes of ``tests/data/corpus``.  Each comes with its own ``GenerateParams`` (seed, candidates, sampling,
now and then a face-count target).  Nothing here depends on files outside the repository.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from fastmesh.evaluation.primitives import RANDOM_KINDS, posed, random_shape
from fastmesh.params import GenerateParams, TunedParams
from fastmesh.shapes.io import load_shape
from fastmesh.shapes.shape import Shape

SMOOTH = ("ellipsoid", "torus", "wavy", "superellipsoid")
CORPUS = Path(__file__).parent / "data" / "corpus"
FACES_500V = 850  # a face-count target whose result has about 500 vertices (1.7 faces per vertex)


def _surface(kind: str, rng: np.random.Generator, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(n,) parameters in [0, 2 pi) x (0, pi) -> (n, 3) points of a surface of family ``kind``, drawn by ``rng``
    (the same ``rng`` state gives the same surface)."""
    a, b, c = rng.uniform(0.3, 1.0, 3)
    if kind == "ellipsoid":
        return np.c_[a * np.cos(u) * np.sin(v), b * np.sin(u) * np.sin(v), c * np.cos(v)]
    if kind == "torus":
        big, small = rng.uniform(0.5, 1.0), rng.uniform(0.1, 0.4)
        w = 2 * v  # the tube's angle over [0, 2 pi)
        return np.c_[(big + small * np.cos(w)) * np.cos(u), (big + small * np.cos(w)) * np.sin(u), small * np.sin(w)]
    if kind == "wavy":
        k, m, amp = rng.integers(2, 6), rng.integers(2, 6), rng.uniform(0.05, 0.25)
        r = 1.0 + amp * np.sin(k * u) * np.sin(m * v)
        return r[:, None] * np.c_[np.cos(u) * np.sin(v), np.sin(u) * np.sin(v), np.cos(v)]
    if kind == "superellipsoid":
        e = rng.uniform(0.4, 0.8)

        def sp(x):
            return np.sign(x) * np.abs(x) ** e

        return np.c_[a * sp(np.cos(u)) * sp(np.sin(v)), b * sp(np.sin(u)) * sp(np.sin(v)), c * sp(np.cos(v))]
    raise ValueError(f"unknown smooth kind {kind!r}; one of {', '.join(SMOOTH)}")


def smooth_cloud(kind: str, seed: int, n: int = 8192, noise: float = 0.0) -> Shape:
    """``n`` points of a random surface of family ``kind`` with their normals (from the surface's tangents,
    pointing away from its centre), jittered by ``noise`` x its size."""
    rng = np.random.default_rng(seed)
    state = rng.bit_generator.state
    u, v = rng.uniform(0, 2 * np.pi, n), np.arccos(rng.uniform(-0.999, 0.999, n))  # even over a sphere
    surface = np.random.default_rng(0)

    def at(du: float, dv: float) -> np.ndarray:
        surface.bit_generator.state = state  # the same surface for every evaluation
        return _surface(kind, surface, u + du, v + dv)

    h = 1e-4
    p = at(0, 0)
    nrm = np.cross(at(h, 0) - at(-h, 0), at(0, h) - at(0, -h))  # one orientation all over (a regular surface)
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True).clip(1e-12)
    nrm *= np.sign(nrm[p[:, 0].argmax(), 0]) or 1.0  # outward where the surface is furthest along x
    p = p + rng.normal(0, noise * np.ptp(p, axis=0).max(), p.shape)
    return Shape(vertices=p, normals=nrm)


def turned(cloud: Shape, rng: np.random.Generator, millimetres: bool = False) -> Shape:
    """A point cloud (and its normals) turned at random; with ``millimetres`` scaled by 1,000 and moved up to
    10 m, as ``primitives.posed`` does to a mesh."""
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    q[:, 0] *= np.linalg.det(q)  # a rotation, not a reflection
    v = cloud.vertices @ q.T
    if millimetres:
        v = v * 1000.0 + rng.uniform(-1e4, 1e4, 3)
    return Shape(vertices=v, normals=cloud.normals @ q.T)


def corpus_meshes() -> list[Path]:
    """The artist meshes of ``tests/data/corpus`` (base meshes and poses), sorted."""
    return sorted(CORPUS.glob("*/*.ply"))


def varied(n: int, seed: int = 0) -> list[tuple[str, Shape, GenerateParams]]:
    """``n`` inputs of every kind above in turn, each with its own parameters: (name, shape, params)."""
    rng = np.random.default_rng(seed)
    meshes = corpus_meshes()
    out = []
    for i in range(n):
        s = int(rng.integers(0, 2**31))
        params = GenerateParams(seed=s % 1000, candidates=int(rng.integers(1, 3)),
                                temperature=0.0 if i % 7 == 3 else 0.3,
                                target_faces=int(rng.integers(60, 600)) if i % 5 == 4 else None)
        turn = i % 4
        if turn in (0, 1):
            kind = SMOOTH[(i // 4) % len(SMOOTH)]
            shape = smooth_cloud(kind, s, int(rng.integers(1500, 20000)), float(rng.choice([0.0, 0.002, 0.01])))
            shape = turned(shape, rng, millimetres=i % 8 == 1)
            name = f"{kind}-cloud"
        elif turn == 2 and meshes:
            path = meshes[(i // 4) % len(meshes)]
            shape, name = load_shape(path), path.stem.split("__")[-1]
        else:
            kind = RANDOM_KINDS[(i // 4) % len(RANDOM_KINDS)]
            shape, name = posed(random_shape(kind, rng), rng), f"{kind}-mesh"
        out.append((f"{i:03d}-{name}", shape, params))
    return out


def five_hundred(n: int, seed: int = 1) -> list[tuple[str, Shape, GenerateParams]]:
    """``n`` smooth point clouds asked for ``FACES_500V`` faces, told to the decoder (``SamplingConfig.read_count``):
    results of about 500 vertices decoded."""
    return [(f"500v-{SMOOTH[i % len(SMOOTH)]}", smooth_cloud(SMOOTH[i % len(SMOOTH)], seed + i),
             TunedParams({"read_count": True}, GenerateParams(seed=i, target_faces=FACES_500V))) for i in range(n)]
