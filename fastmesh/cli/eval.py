"""``fastmesh eval --inputs DIR --reference DIR [--json] [--gt-vertices] [--baseline] [--save DIR] [--sheets DIR]
[--sampling JSON]``.

Scores the pipeline (and with ``--baseline`` a convex hull and screened Poisson + quadric
decimation, to the reference's face count and to ours) on every input that has a reference
mesh of the same name, as ../shared/EVAL.md defines.  With ``--gt-vertices`` the face stage
alone runs on each reference's vertices; ``--baseline`` then adds the other face selection and
the surface-restricted Delaunay anchor on the same vertices and points.  ``--save DIR`` writes
each result as ``DIR/<input name>.ply`` (the other systems' under ``DIR/<system>/``) in the
reference's original frame.  Every result is also scored by what a renderer shows (back faces seen from 14
views, silhouette overlap and normal angle against the reference, faces wound against their neighbours,
crossing faces, unwelded vertices, faces per reference face: ``fastmesh.evaluation.seen``); ``--sheets DIR``
writes a picture per shape beside them.  Make such folders from a dataset's validation split with
``fastmesh data eval-set``.
"""

from __future__ import annotations

import json
import sys

from fastmesh.params import TunedParams

from .flags import params_from_args
from .generate import add_sampling_args, load_pipeline


def register(sub) -> None:
    p = sub.add_parser("eval", help="measure CD/HD (or face-stage edge F1) against reference meshes")
    p.add_argument("--inputs", required=True, metavar="DIR", help="point clouds (or meshes) to generate from")
    p.add_argument("--reference", required=True, metavar="DIR", help="reference meshes, same names")
    p.add_argument("--gt-vertices", action="store_true",
                   help="score the face stage alone on each reference's 7-bit vertices")
    p.add_argument("--baseline", action="store_true",
                   help="also score convex hull and screened Poisson + decimation to the reference's face count and to "
                        "ours (needs pymeshlab), and for mesh "
                        "inputs quadric decimation of the input to our face count; with --gt-vertices the other "
                        "face selection and the restricted Delaunay anchor")
    p.add_argument("--save", metavar="DIR", help="write every result as DIR/<input name>.ply (reference frame)")
    p.add_argument("--sheets", metavar="DIR",
                   help="write DIR/<input name>.png per shape: reference, ours and screened Poisson + decimation to "
                        "our face count (needs pymeshlab), shaded with back faces red and as wireframes")
    p.add_argument("--limit", type=int, default=0, help="only the first N pairs")
    p.add_argument("--json", action="store_true", help="print the whole report as JSON")
    p.add_argument("--sampling", metavar="JSON", default=None,
                   help='decoder settings a request does not carry, to measure them, e.g. \'{"snap_margin": 1.0}\'')
    add_sampling_args(p)
    p.set_defaults(func=_run)


def _run(args) -> int:
    from fastmesh.evaluation.eval import evaluate_end_to_end, evaluate_gt_vertices, pair_inputs
    from fastmesh.shapes.io import load_shape

    pairs = pair_inputs(args.inputs, args.reference)
    if args.limit:
        pairs = pairs[: args.limit]
    pipe = load_pipeline(args)
    params = params_from_args(args)
    if args.sampling is not None:
        try:
            overrides = json.loads(args.sampling)
        except json.JSONDecodeError as e:
            raise ValueError(f"--sampling is not JSON: {e}") from None
        params = TunedParams(overrides, params)
    params.validate(limit=pipe.max_vertices)
    log = lambda s: print(s, file=sys.stderr, flush=True)  # noqa: E731
    if args.gt_vertices:
        report = evaluate_gt_vertices(pipe, pairs, filtering=params.filtering, seed=params.seed,
                                      max_vertices=args.max_vertices, log=log, baseline=args.baseline,
                                      save=args.save)
    else:
        systems = ["fastmesh"]
        if args.baseline or args.sheets:
            try:
                import pymeshlab  # noqa: F401
            except ImportError:
                flag = "--baseline" if args.baseline else "--sheets"
                raise ValueError(f"{flag} needs pymeshlab: pip install -e '.[bench]'") from None
        if args.baseline:
            systems += ["convex_hull", "poisson", "poisson_ours"]
            if any(inp.suffix.lower() != ".npz" and load_shape(inp).faces is not None for inp, _ in pairs[:1]):
                systems.append("decimation")  # mesh inputs: decimated to our face count
        elif args.sheets:
            systems.append("poisson_ours")  # the sheets' classical anchor
        report = evaluate_end_to_end(pipe, pairs, params, systems=systems, log=log, save=args.save,
                                     sheets=args.sheets)
    report["weights"] = pipe.source
    if args.json:
        print(json.dumps(report, indent=2))
    else:
        print(json.dumps(report["summary"], indent=2))
    return 0
