"""``fastmesh generate INPUT -o OUTPUT``: point cloud or mesh in, artist mesh out.

INPUT may be a folder: then OUTPUT is a folder and every shape in INPUT (:mod:`fastmesh.cli.inputs` says which
files are) is done, one line of progress per file on stderr; ``IN/a/chair.off`` becomes ``OUT/a/chair.off.glb``.
``--json`` prints one JSON object per input on stdout.
"""

from __future__ import annotations

import argparse
import json
import sys
import time

from fastmesh.shapes.shape import EXPORT_FORMATS

TIMING_KEYS = ("load", "encode", "vertices", "enhancer", "faces", "filtering", "export", "total")


def add_sampling_args(p) -> None:
    """Flags shared by ``generate`` and ``eval``."""
    from fastmesh.params import CLOSED_CHOICES, GenerateParams

    d = GenerateParams()
    p.add_argument("--seed", type=int, default=d.seed)
    p.add_argument("--temperature", type=float, default=d.temperature, help="0 = greedy")
    p.add_argument("--top-k", type=int, default=d.top_k, help="0 disables")
    p.add_argument("--top-p", type=float, default=d.top_p)
    p.add_argument("--max-vertices", type=int, default=None, help="default: the model's limit")
    p.add_argument("--target-faces", type=int, default=None, metavar="N",
                   help="faces to aim for, held within 20 %% (default: the model chooses the count from the shape)")
    p.add_argument("--closed", choices=CLOSED_CHOICES, default=d.closed,
                   help="close the result's holes: auto = when the input is closed (a closed mesh, or oriented points "
                        "that enclose a volume)")
    p.add_argument("--candidates", type=int, default=d.candidates,
                   help="meshes sampled (seeds SEED, SEED+1, ...); the one nearest the input is kept "
                        "(1 = fastest)")
    p.add_argument("--no-enhancer", action="store_true", help="skip the fidelity enhancer (7-bit cell centres)")
    p.add_argument("--filtering", action=argparse.BooleanOptionalAction, default=d.filtering,
                   help="prediction filtering: masked re-predictions of the edges (default: off, one face pass)")
    p.add_argument("--weights", metavar="DIR", help="weights folder (default: the shipped weights)")
    p.add_argument("--device", help="cpu, cuda, cuda:1 ... (default: cuda when present)")
    p.add_argument("--threads", type=int, default=None,
                   help="torch threads (default: $FASTMESH_TORCH_THREADS, else 1 on CPU, the fastest for one mesh "
                        "at a time)")


def add_output_args(p, defaults: bool = True) -> None:
    """Flags of the written result (``fastmesh.export.output``), shared by ``generate`` and ``submit``; without
    ``defaults`` an unset flag is None (the server's default)."""
    from fastmesh.params import ORIGIN_CHOICES, TOPOLOGY_CHOICES, UP_CHOICES, GenerateParams

    d = GenerateParams()

    def default(value):
        return value if defaults else None

    p.add_argument("--topology", choices=TOPOLOGY_CHOICES, default=default(d.topology),
                   help="quad: pairs of triangles that make a near-planar, well-shaped quad become one (OBJ and PLY; "
                        "GLB holds triangles)")
    p.add_argument("--uv", action=argparse.BooleanOptionalAction, default=default(d.uv),
                   help="a UV layout (xatlas) in the GLB (TEXCOORD_0) and OBJ (vt) files")
    p.add_argument("--bake", action=argparse.BooleanOptionalAction, default=default(d.bake),
                   help="with --uv: bake a textured glTF input's base colour onto the layout (GLB texture)")
    p.add_argument("--origin", choices=ORIGIN_CHOICES, default=default(d.origin),
                   help="the result's origin: the input's frame, its bounding-box centre, or its bottom centre (Y up)")
    p.add_argument("--height", type=float, default=None, metavar="METRES",
                   help="scale the result to stand this tall along Y (default: the input's size)")
    p.add_argument("--up", choices=UP_CHOICES, default=default(d.up),
                   help="up axis of OBJ and PLY files (GLB is always Y-up)")


def output_params(args) -> dict:
    """The output flags of ``args`` as GenerateParams fields."""
    return {k: getattr(args, k) for k in ("topology", "uv", "bake", "origin", "height", "up")}


def params_from_args(args):
    from fastmesh.params import GenerateParams

    extra = output_params(args) if hasattr(args, "topology") else {}
    return GenerateParams(seed=args.seed, temperature=args.temperature, top_k=args.top_k, top_p=args.top_p,
                          max_vertices=args.max_vertices, enhancer=not args.no_enhancer,
                          filtering=args.filtering, candidates=args.candidates,
                          target_faces=args.target_faces, closed=args.closed, **extra)


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
    p.add_argument("-o", "--output", required=True, metavar="OUTPUT")
    p.add_argument("--format", choices=EXPORT_FORMATS, default=None,
                   help="default: OUTPUT's extension, else glb (a file OUTPUT's extension must match it)")
    p.add_argument("--glob", metavar="PATTERN", default=None,
                   help="with a folder INPUT: the files to do, relative to it ('*.ply', '**/*.obj'; default: every "
                        "shape below it)")
    add_sampling_args(p)
    add_output_args(p)
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
               "timings": {k: round(timings.get(k, 0.0), 4) for k in TIMING_KEYS}, "quality": res.quality,
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
