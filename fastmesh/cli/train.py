"""``fastmesh train {vertex,enhancer,face,cells} --data FILE --out DIR [--config FILE] [--resume]``.

Multi-process: ``torchrun --nproc_per_node 2 -m fastmesh.cli train vertex ...`` (DDP; gloo on
CPU, nccl on GPUs).
"""

from __future__ import annotations

import json
import os
import sys


def register(sub) -> None:
    p = sub.add_parser("train", help="train one of the three networks on a dataset cache")
    p.add_argument("network", choices=["vertex", "enhancer", "face", "cells"])
    p.add_argument("--data", required=True, metavar="FILE", help="cache from `fastmesh data build`")
    p.add_argument("--out", required=True, metavar="DIR", help="checkpoint folder")
    p.add_argument("--config", metavar="FILE", help="JSON TrainConfig (model overrides under \"model\")")
    p.add_argument("--resume", action="store_true", help="continue from DIR/train_state.pt exactly")
    p.add_argument("--init", metavar="DIR",
                   help="start from saved weights (e.g. fastmesh/weights/vertex) with a fresh optimizer")
    p.add_argument("--set", action="append", default=[], metavar="KEY=JSON",
                   help="override one TrainConfig field, e.g. --set steps=100 --set max_minutes=5")
    p.set_defaults(func=_run)


def _run(args) -> int:
    from fastmesh.training.loop import load_train_config, train
    from fastmesh.training.tasks import TASKS

    if args.network not in TASKS:
        raise ValueError(f"training for '{args.network}' is not available")
    if not os.path.exists(args.data):
        raise FileNotFoundError(f"no dataset cache at {args.data}; build one with `fastmesh data build`")
    overrides = {}
    for kv in args.set:
        key, sep, val = kv.partition("=")
        if not sep:
            raise ValueError(f"--set expects KEY=JSON, got {kv!r}")
        try:
            overrides[key] = json.loads(val)
        except json.JSONDecodeError:
            overrides[key] = val
    cfg = load_train_config(args.config, overrides)
    if args.resume and not os.path.exists(os.path.join(args.out, "train_state.pt")):
        print(f"fastmesh train: nothing to resume in {args.out}; starting fresh", file=sys.stderr)
    if args.init and args.resume:
        raise ValueError("--init and --resume exclude each other")
    train(TASKS[args.network](), args.data, args.out, cfg, resume=args.resume, init=args.init,
          log=lambda s: print(s, file=sys.stderr, flush=True))
    return 0
