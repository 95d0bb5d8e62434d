"""topology=quad on artist meshes' point clouds: how many quads the face model's flat 4-cliques make, and the quad
share and shape with that evidence and by shape alone (fastmesh.export.quads.pair_triangles).

Usage: python benchmarks/quad_cliques.py MESH.ply ... [--points 8192] [--seed 0]

Each mesh is sampled (points with their face normals, fixed seed) and run through the shipped weights on the
CPU with ``topology=quad``; the result's triangles are paired twice: with the face stage's evidence (what the
pipeline writes) and without it.  One JSON line per mesh, then the totals, with the quantiles of the
probabilities the model gave the candidates' diagonals and weakest sides and the result's edges.  The corpus
keeps triangles only (its README: polygons were fan-triangulated), so the quads cannot be compared with the
artist's own.
"""

from __future__ import annotations

import argparse
import json

import numpy as np
import trimesh

import fastmesh.export.output
from fastmesh.export import quads
from fastmesh.params import GenerateParams
from fastmesh.pipeline import Pipeline
from fastmesh.shapes.io import load_shape
from fastmesh.shapes.shape import Shape


def worst_corner(vertices: np.ndarray, faces: np.ndarray, pairs: np.ndarray) -> float | None:
    """Mean over the quads of their worst corner's distance from 90 degrees (None without quads)."""
    if len(pairs) == 0:
        return None
    c = np.asarray(vertices, dtype=np.float64)[quads.quad_corners(faces, pairs)]
    into, back = np.roll(c, -1, axis=1) - c, np.roll(c, 1, axis=1) - c
    cos = np.sum(into * back, axis=2) / (np.linalg.norm(into, axis=2) * np.linalg.norm(back, axis=2))
    return round(float(np.mean(np.abs(np.degrees(np.arccos(np.clip(cos, -1, 1))) - 90).max(axis=1))), 2)


def candidates(vertices: np.ndarray, faces: np.ndarray, config: quads.QuadConfig) -> np.ndarray:
    """(P, 4) corners of the candidate quads within ``config``'s shape limits."""
    pairs = quads.interior_pairs(faces)
    tri = vertices[faces]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    corners = quads.quad_corners(faces, pairs)
    score = quads.quad_scores(vertices, corners, n[pairs[:, 0]], n[pairs[:, 1]], config)
    return corners[np.isfinite(score)]


def measure(pipe: Pipeline, path: str, n_points: int, seed: int, probs: dict) -> dict:
    """One mesh's row; adds to ``probs`` the probabilities of its candidates' diagonals and weakest sides and of
    its result's edges (lists under "diagonal", "side" and "edge")."""
    src = load_shape(path)
    mesh = trimesh.Trimesh(src.vertices, src.faces, process=False)
    points, index = trimesh.sample.sample_surface(mesh, n_points, seed=seed)
    shape = Shape(vertices=np.asarray(points), faces=None, normals=np.asarray(mesh.face_normals[index]))
    seen = []

    def spy(vertices, faces, config=None, evidence=None):
        seen.append((np.asarray(vertices, dtype=np.float64), np.asarray(faces), evidence))
        return quads.pair_triangles(vertices, faces, config, evidence)

    fastmesh.export.output.pair_triangles = spy
    res = pipe.generate(shape, GenerateParams(topology="quad", seed=seed))
    v, f, evidence = seen[0]
    shape_only = quads.pair_triangles(v, f)
    row = {"mesh": path.rsplit("/", 1)[-1], "input_faces": len(src.faces), "faces": len(f),
           "result_from": res.info["result_from"], "quads": res.quality["quads"],
           "quad_share": res.quality["quad_share"], "quads_shape_only": len(shape_only),
           "quad_share_shape_only": quads.quad_share(len(shape_only), len(f) - 2 * len(shape_only)),
           "worst_corner": worst_corner(v, f, res.mesh.pairs),
           "worst_corner_shape_only": worst_corner(v, f, shape_only)}
    if evidence is not None:
        edges = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
        cand = candidates(v, f, quads.QuadConfig())
        cliques = quads.flat_cliques(v, cand, evidence, quads.QuadConfig())
        written = {frozenset(q) for q in quads.quad_corners(f, res.mesh.pairs).tolist()}
        sides = np.stack([cand, np.roll(cand, -1, axis=1)], axis=2).reshape(-1, 2)
        probs["diagonal"] += evidence.probabilities(v, cand[:, [0, 2]]).tolist()
        probs["side"] += evidence.probabilities(v, sides).reshape(-1, 4).min(axis=1).tolist()
        probs["edge"] += evidence.probabilities(v, edges).tolist()
        row.update({"edges_with_evidence": round(float(np.isfinite(evidence.probabilities(v, edges)).mean()), 3),
                    "candidates": len(cand), "cliques": int(cliques.sum()),
                    "clique_quads_written": sum(frozenset(q) in written for q in cand[cliques].tolist())})
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("meshes", nargs="+")
    ap.add_argument("--points", type=int, default=8192)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    pipe = Pipeline.from_pretrained(device="cpu")
    rows, probs = [], {"diagonal": [], "side": [], "edge": []}
    for path in args.meshes:
        rows.append(measure(pipe, path, args.points, args.seed, probs))
        print(json.dumps(rows[-1]), flush=True)
    total = {k: sum(r.get(k, 0) for r in rows) for k in ("faces", "quads", "quads_shape_only", "candidates",
                                                         "cliques", "clique_quads_written")}
    for k in ("quad_share", "quad_share_shape_only", "worst_corner", "worst_corner_shape_only"):
        vals = [r[k] for r in rows if r[k] is not None]
        total[f"mean_{k}"] = round(float(np.mean(vals)), 4) if vals else None
    for name, p in probs.items():  # NaN (a side, diagonal or edge without evidence) compares False: left out
        p = np.asarray(p)[np.isfinite(p)]
        if len(p):
            total[f"{name}_prob_q10_q50_q90"] = np.round(np.quantile(p, [0.1, 0.5, 0.9]), 3).tolist()
            total[f"{name}_prob_below_half"] = round(float(np.mean(p < 0.5)), 3)
    print(json.dumps({"meshes": len(rows), **total}))


if __name__ == "__main__":
    main()
