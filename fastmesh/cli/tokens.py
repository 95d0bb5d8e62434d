"""``fastmesh tokens PATH... [--json]``: sequence lengths of vanilla, BPT and FastMesh tokens per mesh."""

from __future__ import annotations

import json
import sys
from pathlib import Path

from fastmesh.shapes.shape import MESH_FORMATS


def register(sub) -> None:
    p = sub.add_parser("tokens", help="count vanilla / BPT / FastMesh tokens of meshes after 7-bit quantisation")
    p.add_argument("paths", nargs="+", metavar="PATH", help="mesh files or folders (searched recursively)")
    p.add_argument("--json", action="store_true", help="print one JSON object instead of a table")
    p.add_argument("--workers", type=int, default=1, help="processes (default 1)")
    p.set_defaults(func=_run)


def mesh_files(paths: list[str]) -> list[str]:
    """Files named on the command line, plus mesh files found under named folders (sorted)."""
    out = []
    for p in map(Path, paths):
        if p.is_dir():
            out += sorted(str(f) for f in p.rglob("*") if f.is_file() and f.suffix.lower().lstrip(".") in MESH_FORMATS)
        else:
            out.append(str(p))  # missing or unsupported files fail in count_tokens with a clear message
    return out


def count_tokens(path: str) -> dict:
    """Token counts of one mesh file; ``{"file", "error", "code"}`` when it cannot be used."""
    from fastmesh.shapes.io import load_shape
    from fastmesh.shapes.shape import Normalization, ShapeError
    from fastmesh.tokenizer import bpt, quantize_mesh, vanilla, vertex

    try:
        shape = load_shape(path)
        if shape.faces is None:
            raise ShapeError("not_a_mesh", "file holds a point cloud, not a mesh")
        v = Normalization.fit(shape.vertices).apply(shape.vertices)
        q, faces, _ = quantize_mesh(v, shape.faces)
        if len(faces) == 0:
            raise ShapeError("degenerate", "no face survives 7-bit quantisation")
    except ShapeError as e:
        return {"file": path, "error": e.message, "code": e.code}
    return {"file": path, "vertices": len(q), "faces": len(faces), "vanilla": vanilla.num_tokens(q, faces),
            "bpt": bpt.num_tokens(q, faces), "fastmesh": vertex.num_tokens(q)}


def summarize(rows: list[dict]) -> dict:
    """The ``total`` object: sums over usable meshes and the ratios."""
    ok = [r for r in rows if "error" not in r]
    tot = {k: sum(r[k] for r in ok) for k in ("vertices", "faces", "vanilla", "bpt", "fastmesh")}
    tot["meshes"], tot["failed"] = len(ok), len(rows) - len(ok)
    tot["ratio_fastmesh_bpt"] = tot["fastmesh"] / tot["bpt"] if tot["bpt"] else None
    tot["ratio_bpt_vanilla"] = tot["bpt"] / tot["vanilla"] if tot["vanilla"] else None
    return tot


def _run(args) -> int:
    files = mesh_files(args.paths)
    if not files:
        raise ValueError("no mesh files found in " + ", ".join(args.paths))
    if args.workers > 1 and len(files) > 1:
        from concurrent.futures import ProcessPoolExecutor

        with ProcessPoolExecutor(args.workers) as ex:
            rows = list(ex.map(count_tokens, files, chunksize=16))
    else:
        rows = [count_tokens(f) for f in files]
    failed = [r for r in rows if "error" in r]
    for r in failed:
        print(f"fastmesh tokens: {r['file']}: {r['error']}", file=sys.stderr)
    total = summarize(rows)
    if args.json:
        print(json.dumps({"meshes": [r for r in rows if "error" not in r], "total": total, "failed": failed}))
    else:
        line = "{vertices:>9} {faces:>7} {vanilla:>8} {bpt:>7} {fastmesh:>8}  {file}"
        print(line.format(vertices="vertices", faces="faces", vanilla="vanilla", bpt="bpt", fastmesh="fastmesh",
                          file="file"))
        for r in rows:
            if "error" not in r:
                print(line.format(**r))
        print(line.format(**{**total, "file": f"total ({total['meshes']} meshes, {total['failed']} failed)"}))
        if total["bpt"]:
            print(f"fastmesh/bpt = {total['ratio_fastmesh_bpt']:.4f}   bpt/vanilla = {total['ratio_bpt_vanilla']:.4f}")
    return 1 if failed else 0
