"""``fastmesh data build SRC... -o FILE [--max-vertices N]`` and ``fastmesh data stats FILE``."""

from __future__ import annotations

import json
import sys
import time

from fastmesh.training.data import VAL_PACKAGES


def register(sub) -> None:
    p = sub.add_parser("data", help="build and inspect training-set caches")
    dsub = p.add_subparsers(dest="data_command", required=True)
    b = dsub.add_parser("build",
                        help="quantise, merge, de-duplicate and split mesh folders into one cache file")
    b.add_argument("sources", nargs="+", metavar="SRC", help="mesh files or folders (searched recursively)")
    b.add_argument("-o", "--out", required=True, metavar="FILE", help="cache file to write (.npz)")
    b.add_argument("--max-vertices", type=int, default=1000,
                   help="drop meshes with more vertices after the 7-bit merge")
    b.add_argument("--val-packages", default=None, metavar="P1,P2,...",
                   help="packages held out whole for validation (default: those of "
                        f"{','.join(VAL_PACKAGES)} among the sources; with none of them, a split by group); "
                        "'none' splits by group with --val-fraction")
    b.add_argument("--val-fraction", type=float, default=0.05,
                   help="with --val-packages none: share of groups held out (0: train on everything)")
    b.add_argument("--workers", type=int, default=None, help="processes (default: all cores)")
    b.set_defaults(func=_build)
    s = dsub.add_parser("stats", help="print statistics of a cache file (JSON)")
    s.add_argument("file")
    s.set_defaults(func=_stats)
    e = dsub.add_parser("eval-set",
                        help="write a split as inputs/ (point clouds) + reference/ (meshes) for `fastmesh eval`")
    e.add_argument("file", help="cache file")
    e.add_argument("--source", required=True, metavar="DIR", help="folder the cache was built from")
    e.add_argument("-o", "--out", required=True, metavar="DIR")
    e.add_argument("--split", choices=["val", "train", "all"], default="val")
    e.add_argument("--points", type=int, default=8192, help="samples per input point cloud")
    e.add_argument("--max-vertices", type=int, default=0, help="only meshes up to this many (7-bit) vertices")
    e.add_argument("--per-package", type=int, default=0, metavar="N",
                   help="only N meshes of each package, evenly spread (a small set that holds every package)")
    e.add_argument("--dense-meshes", type=int, default=0, metavar="FACES",
                   help="inputs as dense meshes of about FACES faces (isotropic remeshing of each reference, "
                        "needs pymeshlab) instead of point clouds")
    e.set_defaults(func=_eval_set)
    c = dsub.add_parser("cells", help="some meshes of a cache plus the cell evidence network's log-odds of each "
                                      "(training data of a decoder that reads them)")
    c.add_argument("file", help="cache file")
    c.add_argument("--weights", required=True, metavar="DIR", help="a trained cell evidence network")
    c.add_argument("-o", "--out", required=True, metavar="FILE")
    c.add_argument("--train", type=int, default=1000, metavar="N", help="training meshes to take")
    c.add_argument("--val", type=int, default=64, metavar="N", help="validation meshes to take")
    c.add_argument("--seed", type=int, default=0)
    c.add_argument("--workers", type=int, default=1, metavar="N", help="processes scoring meshes side by side")
    c.set_defaults(func=_cells)


def _build(args) -> int:
    from fastmesh.training.data import build_dataset

    if args.max_vertices < 3:
        raise ValueError("--max-vertices must be at least 3")
    if not 0 <= args.val_fraction < 1:
        raise ValueError("--val-fraction must be in [0, 1)")
    given = args.val_packages
    if given is None:
        packages = VAL_PACKAGES
    elif given.strip().lower() in ("", "none"):
        packages = ()
    else:
        packages = tuple(p.strip() for p in given.split(",") if p.strip())
    t = time.perf_counter()
    stats = build_dataset(args.sources, args.out, max_vertices=args.max_vertices, val_fraction=args.val_fraction,
                          val_packages=packages, missing_ok=given is None, workers=args.workers,
                          progress=lambda i, n: print(f"  {i}/{n} files", file=sys.stderr))
    stats["seconds"] = round(time.perf_counter() - t, 2)
    print(json.dumps(stats, indent=2))
    return 0


def _stats(args) -> int:
    from fastmesh.training.data import dataset_stats, load_dataset

    print(json.dumps(dataset_stats(load_dataset(args.file)), indent=2))
    return 0


def _cells(args) -> int:
    from fastmesh.models.checkpoint import load_model
    from fastmesh.training.data import build_cell_cache, load_dataset

    net = load_model(args.weights, device="cpu")[0]  # forked workers score on the CPU
    if net.cfg.__class__.__name__ != "CellNetConfig":
        raise ValueError(f"{args.weights} holds no cell evidence network")
    t = time.perf_counter()
    def progress(i: int, n: int) -> None:
        if i % 100 == 0:
            print(f"  {i}/{n}", file=sys.stderr, flush=True)

    n = build_cell_cache(load_dataset(args.file), net, args.out, {"train": args.train, "val": args.val},
                         seed=args.seed, workers=args.workers, progress=progress)
    print(f"wrote {n} meshes with cell log-odds to {args.out} in {time.perf_counter() - t:.0f} s")
    return 0


def _eval_set(args) -> int:
    from fastmesh.evaluation.eval import export_eval_set
    from fastmesh.training.data import load_dataset

    n = export_eval_set(load_dataset(args.file), args.source, args.out, split=args.split, n_points=args.points,
                        max_vertices=args.max_vertices or None, per_package=args.per_package or None,
                        dense_faces=args.dense_meshes or None)
    print(f"wrote {n} input/reference pairs to {args.out}")
    return 0
