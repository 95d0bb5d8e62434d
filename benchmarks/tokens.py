"""Token counts over a mesh corpus, time to tokenise it, and the faces-from-adjacency check.

    python benchmarks/tokens.py [CORPUS] [--stride K] [--workers N]

CORPUS defaults to ../shared/corpus beside the repository.  For every mesh (normalised,
7-bit quantised and merged as the models see it):

* tokens of the vanilla (9 per face), BPT and FastMesh vertex tokenizers, per vertex, and
  the ratio fastmesh/bpt (the paper reports about 0.23);
* seconds spent encoding with each tokenizer (after loading and quantising);
* the ground-truth adjacency (edges of the faces) turned back into triangles: every ground
  truth triangle must be recovered; the 3-cycles that are not faces ("extra") are counted
  before clean-up, after dropping zero-area triangles, after also dropping the outer
  triangle of flat 4-cliques with an inner point, and after also dropping the longer
  diagonal of flat convex 4-cliques (``faces.drop_coplanar_diagonals``), together with the
  ground-truth faces each clean-up removes.

Prints a plain-text report; ``--json`` prints the numbers as one object.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from fastmesh.faces import cliques, orient  # noqa: E402
from fastmesh.faces import triangles as trimod  # noqa: E402
from fastmesh.faces.meshops import edges_from_faces  # noqa: E402
from fastmesh.shapes.io import load_shape  # noqa: E402
from fastmesh.shapes.shape import Normalization, ShapeError  # noqa: E402
from fastmesh.tokenizer import bpt, dequantize, quantize_mesh, vanilla, vertex  # noqa: E402

KEYS = ("vertices", "faces", "vanilla", "bpt", "bpt_authors", "bpt_undirected", "fastmesh")


def _face_keys(f: np.ndarray, n: int) -> np.ndarray:
    s = np.sort(f, axis=1)
    return (s[:, 0] * n + s[:, 1]) * n + s[:, 2]


def measure(path: str) -> dict:
    """All figures for one mesh file (or ``{"error": ...}``)."""
    t0 = time.perf_counter()
    try:
        shape = load_shape(path)
        if shape.faces is None:
            return {"file": path, "error": "point cloud"}
    except ShapeError as e:
        return {"file": path, "error": e.message}
    v = Normalization.fit(shape.vertices).apply(shape.vertices)
    q, f, _ = quantize_mesh(v, shape.faces)
    t1 = time.perf_counter()
    r = {"file": path, "vertices": len(q), "faces": len(f), "load_s": t1 - t0}
    t = time.perf_counter()
    r["fastmesh"] = len(vertex.encode(q))
    r["fastmesh_s"] = time.perf_counter() - t
    t = time.perf_counter()
    r["bpt"] = len(bpt.encode(q, f))
    r["bpt_s"] = time.perf_counter() - t
    t = time.perf_counter()
    r["vanilla"] = len(vanilla.encode(q, f))
    r["vanilla_s"] = time.perf_counter() - t
    r["bpt_authors"] = bpt.num_tokens(q, f, oriented=False, first_block_explicit=True)
    r["bpt_undirected"] = bpt.num_tokens(q, f, oriented=False)

    # Faces from the ground-truth adjacency.
    n, x = len(q), dequantize(q)
    gt = _face_keys(f, n)
    t = time.perf_counter()
    tri = cliques.triangles_from_adjacency(edges_from_faces(f), n)
    r["tri_s"] = time.perf_counter() - t
    r["gt_missing"] = int((~np.isin(gt, _face_keys(tri, n))).sum())
    r["extra_raw"] = len(tri) - (len(f) - r["gt_missing"])
    t = time.perf_counter()
    c1 = trimod.drop_degenerate(x, tri)
    c3 = trimod.drop_coplanar_diagonals(x, c1)
    orient.orient_faces(x, c3)
    r["clean_s"] = time.perf_counter() - t
    c2 = trimod.drop_coplanar_diagonals(x, c1, cases=("inner",))
    for name, c in (("zero_area", c1), ("inner", c2), ("coplanar", c3)):
        kept = int(np.isin(gt, _face_keys(c, n)).sum())
        r[f"gt_lost_{name}"] = len(f) - kept
        r[f"extra_{name}"] = len(c) - kept
    return r


def report(rows: list[dict], wall: float) -> dict:
    ok = [r for r in rows if "error" not in r]
    tot = {k: int(sum(r[k] for r in ok)) for k in KEYS}
    sec = {k: float(sum(r[k] for r in ok)) for k in ("load_s", "fastmesh_s", "bpt_s", "vanilla_s", "tri_s", "clean_s")}
    per_mesh = np.array([r["fastmesh"] / r["bpt"] for r in ok])
    small = [r for r in ok if r["vertices"] <= 1000]
    check_keys = ("gt_missing", "extra_raw", "extra_zero_area", "extra_inner", "extra_coplanar",
                  "gt_lost_zero_area", "gt_lost_inner", "gt_lost_coplanar")
    faces_check = {k: int(sum(r[k] for r in ok)) for k in check_keys}
    faces_check["meshes_with_extra_raw"] = int(sum(r["extra_raw"] > 0 for r in ok))
    return {
        "meshes": len(ok), "failed": len(rows) - len(ok), "totals": tot, "seconds": sec, "wall_s": wall,
        "tokens_per_vertex": {k: tot[k] / tot["vertices"] for k in KEYS[2:]},
        "ratio_fastmesh_bpt": tot["fastmesh"] / tot["bpt"],
        "ratio_fastmesh_bpt_authors": tot["fastmesh"] / tot["bpt_authors"],
        "ratio_bpt_vanilla": tot["bpt"] / tot["vanilla"],
        "ratio_per_mesh": {"median": float(np.median(per_mesh)), "p10": float(np.quantile(per_mesh, 0.1)),
                           "p90": float(np.quantile(per_mesh, 0.9))},
        "ratio_fastmesh_bpt_le1000v": sum(r["fastmesh"] for r in small) / max(sum(r["bpt"] for r in small), 1),
        "meshes_le1000v": len(small),
        "faces_check": faces_check,
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("corpus", nargs="?", default=str(ROOT.parent / "shared" / "corpus"))
    ap.add_argument("--stride", type=int, default=1, help="use every K-th file (quick runs)")
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    files = sorted(str(p) for p in Path(args.corpus).rglob("*.ply"))[:: args.stride]
    if not files:
        print(f"no .ply files under {args.corpus}", file=sys.stderr)
        return 2
    t = time.perf_counter()
    if args.workers > 1:
        from concurrent.futures import ProcessPoolExecutor

        with ProcessPoolExecutor(args.workers) as ex:
            rows = list(ex.map(measure, files, chunksize=16))
    else:
        rows = [measure(f) for f in files]
    rep = report(rows, time.perf_counter() - t)
    if args.json:
        print(json.dumps(rep, indent=2))
        return 0
    tot, sec, fc = rep["totals"], rep["seconds"], rep["faces_check"]
    print(f"corpus {args.corpus}: {rep['meshes']} meshes ({rep['failed']} failed), "
          f"{tot['vertices']} vertices, {tot['faces']} faces after 7-bit quantisation and merge")
    print("tokens per vertex: " + ", ".join(f"{k} {v:.3f}" for k, v in rep["tokens_per_vertex"].items()))
    print(f"fastmesh/bpt = {rep['ratio_fastmesh_bpt']:.4f} (per mesh median {rep['ratio_per_mesh']['median']:.3f}, "
          f"p10 {rep['ratio_per_mesh']['p10']:.3f}, p90 {rep['ratio_per_mesh']['p90']:.3f}); "
          f"vs the authors' BPT count {rep['ratio_fastmesh_bpt_authors']:.4f}; "
          f"meshes <= 1000 vertices {rep['ratio_fastmesh_bpt_le1000v']:.4f} ({rep['meshes_le1000v']})")
    print(f"bpt/vanilla = {rep['ratio_bpt_vanilla']:.4f}")
    print(f"time: load+quantise {sec['load_s']:.1f} s; encode fastmesh {sec['fastmesh_s']:.2f} s, "
          f"bpt {sec['bpt_s']:.2f} s, vanilla {sec['vanilla_s']:.2f} s; wall {rep['wall_s']:.1f} s "
          f"({args.workers} worker(s))")
    n_gt = tot["faces"]
    print(f"faces from ground-truth adjacency: {n_gt - fc['gt_missing']}/{n_gt} ground-truth triangles recovered; "
          f"extra 3-cycles (not faces) {fc['extra_raw']} ({100 * fc['extra_raw'] / n_gt:.2f}% of the faces, in "
          f"{fc['meshes_with_extra_raw']} meshes)")
    print("clean-up steps (cumulative): extra 3-cycles left / ground-truth faces removed")
    print(f"  drop zero-area triangles:                  {fc['extra_zero_area']:8d} / {fc['gt_lost_zero_area']}")
    print(f"  + outer triangle of flat 4-cliques:        {fc['extra_inner']:8d} / {fc['gt_lost_inner']}")
    print(f"  + longer diagonal of flat convex 4-cliques: {fc['extra_coplanar']:7d} / {fc['gt_lost_coplanar']}")
    print(f"time: triangles {sec['tri_s']:.2f} s, clean-up + orientation {sec['clean_s']:.2f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
