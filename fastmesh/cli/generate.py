"""``fastmesh generate INPUT -o OUTPUT``: point cloud or mesh in, artist mesh out.

INPUT may be a folder: then OUTPUT is a folder and every shape in INPUT (:mod:`fastmesh.cli.inputs` says which
files are) is done, one line of progress per file on stderr; ``IN/a/chair.off`` becomes ``OUT/a/chair.off.glb``.
``--json`` prints one JSON object per input on stdout.
"""

from __future__ import annotations

import json
import sys
import time

from fastmesh.shapes.shape import EXPORT_FORMATS

from .flags import add_param_flags, params_from_args

TIMING_KEYS = ("load", "encode", "vertices", "enhancer", "faces", "filtering", "weighing", "export", "total")


def add_sampling_args(p) -> None:
    """Flags shared by ``generate`` and ``eval``: the generation parameters other than the written result's, and
    where the networks run."""
    add_param_flags(p, output=False)
    p.add_argument("--weights", metavar="DIR", help="weights folder (default: the shipped weights)")
    p.add_argument("--device", help="cpu, cuda, cuda:1 ... (default: cuda when present)")
    p.add_argument("--threads", type=int, default=None,
                   help="torch threads (default: $FASTMESH_TORCH_THREADS, else 1 on CPU, the fastest for one mesh "
                        "at a time)")


def faces_text(faces: int, quality: dict) -> str:
    """The faces of a result as the summaries print them: ``"812 faces"``, or with a face count asked for
    ``"812 / 1000 faces (within ±20 %)"`` (``quality``'s ``target_faces`` and ``target_met``)."""
    from fastmesh.faces.facecount import TOLERANCE

    target = quality.get("target_faces")
    if target is None:
        return f"{faces} faces"
    held = "within" if quality.get("target_met") else "outside"
    return f"{faces} / {target} faces ({held} ±{100 * TOLERANCE:.0f} %)"


def load_pipeline(args):
    from fastmesh.pipeline import Pipeline

    return Pipeline.from_pretrained(args.weights, device=args.device, threads=args.threads)


def register(sub) -> None:
    p = sub.add_parser("generate", help="generate an artist mesh from a point cloud or mesh (file or folder)")
    p.add_argument("input", metavar="INPUT")
    p.add_argument("-o", "--output", required=True, metavar="OUTPUT",
                   help=f"a file ending in .{', .'.join(EXPORT_FORMATS)} or with no extension, or a folder when "
                        "INPUT is one")
    p.add_argument("--format", choices=EXPORT_FORMATS, default=None,
                   help="default: OUTPUT's extension, else glb (a file OUTPUT's extension must match it)")
    p.add_argument("--glob", metavar="PATTERN", default=None,
                   help="with a folder INPUT: the files to do, relative to it ('*.ply', '**/*.obj'; default: every "
                        "shape below it)")
    add_sampling_args(p)
    add_param_flags(p, output=True)
    p.add_argument("--json", action="store_true", help="one JSON object per input on stdout")
    p.set_defaults(func=_run)


def _run(args) -> int:
    from fastmesh.shapes.io import load_shape
    from fastmesh.shapes.shape import ShapeError

    from .inputs import generate_jobs

    params = params_from_args(args)
    jobs, skipped = generate_jobs(args.input, args.output, args.format, args.glob)  # before the slow torch import
    for path, reason in skipped:
        print(f"skipped {path}: {reason}", file=sys.stderr)
    from fastmesh.pipeline import GenerationError

    pipe = load_pipeline(args)
    params.validate(limit=pipe.max_vertices)
    failures = 0
    for i, (src, dst, fmt) in enumerate(jobs, 1):
        t0 = time.perf_counter()
        try:
            shape = load_shape(src, texture=params.bake)
            t_load = time.perf_counter() - t0
            res = pipe.generate(shape, params)
            t = time.perf_counter()
            dst.parent.mkdir(parents=True, exist_ok=True)
            dst.write_bytes(res.export(fmt))
            timings = {"load": t_load, **res.timings, "export": time.perf_counter() - t}
        except (ShapeError, GenerationError) as e:
            failures += 1
            print(f"[{i}/{len(jobs)}] {src}: failed: {e}", file=sys.stderr)
            if args.json:
                print(json.dumps({"input": str(src), "output": None, "error": {"code": e.code, "message": str(e)}}))
            continue
        timings["total"] = time.perf_counter() - t0
        rec = {"input": str(src), "output": str(dst), "vertices": int(len(res.vertices)),
               "faces": int(len(res.faces)), "tokens": res.tokens,
               "timings": {k: round(timings.get(k, 0.0), 4) for k in TIMING_KEYS},
               "result_from": res.info["result_from"], "vertices_from": res.info["vertices_from"],
               "quality": res.quality,
               "placement": res.info.get("placement"), "notes": res.info.get("notes") or []}
        if args.json:
            print(json.dumps(rec), flush=True)
        q = res.quality
        print(f"[{i}/{len(jobs)}] {src} -> {dst}: {rec['vertices']} vertices, {faces_text(rec['faces'], q)}, "
              f"CD {q['cd']:.2f} % / HD {q['hd']:.2f} % of the input's size, {q['boundary_edges']} open edges, "
              f"{timings['total']:.2f} s", file=sys.stderr, flush=True)
        if params.topology == "quad":
            print(f"  {q['quads']} quads ({100 * q['quad_share']:.0f} % of the polygons)", file=sys.stderr)
        for note in rec["notes"]:
            print(f"  note: {note}", file=sys.stderr)
    return 1 if failures else 0
