"""``fastmesh metrics A B [--json]``: Chamfer and Hausdorff distance between two shapes (EVAL.md)."""

from __future__ import annotations

import json


def register(sub) -> None:
    p = sub.add_parser("metrics", help="Chamfer / Hausdorff distance between two mesh (or point cloud) files, in %%")
    p.add_argument("a", metavar="A")
    p.add_argument("b", metavar="B")
    p.add_argument("--json", action="store_true", help='print {"cd": x, "hd": y}')
    p.add_argument("--samples", type=int, default=5000, help="surface samples per shape (EVAL.md: 5000)")
    p.add_argument("--seed", type=int, default=0, help="sampling seed")
    p.set_defaults(func=_run)


def _run(args) -> int:
    from fastmesh.evaluation.metrics import surface_distance
    from fastmesh.shapes.io import load_shape
    from fastmesh.shapes.shape import ShapeError

    if args.samples < 1:
        raise ValueError("--samples must be positive")
    shapes = []
    for path in (args.a, args.b):
        try:
            shapes.append(load_shape(path))
        except ShapeError as e:
            raise ValueError(f"{path}: {e.message}") from None
    d = surface_distance(*[(s.vertices, s.faces) for s in shapes], n=args.samples, seed=args.seed)
    if args.json:
        print(json.dumps(d.to_dict()))
    else:
        print(f"CD {d.cd:.4f} %   HD {d.hd:.4f} %   (of the longest bounding-box side)")
    return 0
