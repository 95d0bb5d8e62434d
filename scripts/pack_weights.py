"""Copy trained checkpoints into the package as the default weights (float16).

    python scripts/pack_weights.py --vertex runs/vertex/best --enhancer runs/enhancer/best \
        --face runs/face/best [--cells runs/cells] -o fastmesh/weights

Each source is a folder with model.safetensors + config.json (as ``fastmesh train`` writes).
Training metadata (step, validation loss) is kept in each config.json.  The cell evidence network
(needed by a decoder trained with it) is small and kept in float32: the decoder learned the exact
log-odds it gives.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from fastmesh.models.checkpoint import load_model, save_model  # noqa: E402
from fastmesh.pipeline.settings import read_settings, write_settings  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser()
    for n in ("vertex", "enhancer", "face"):
        ap.add_argument(f"--{n}", required=True, metavar="DIR")
    ap.add_argument("--cells", metavar="DIR", help="the cell evidence network, for a decoder that reads it")
    ap.add_argument("-o", "--out", default="fastmesh/weights")
    args = ap.parse_args()
    out = Path(args.out)
    for n in ("vertex", "enhancer", "face", "cells"):
        if getattr(args, n) is None:
            continue
        model, meta = load_model(getattr(args, n))
        if meta["kind"] != n:
            raise SystemExit(f"{getattr(args, n)} holds a {meta['kind']} network, not {n}")
        extra = {k: v for k, v in meta.items() if k not in ("kind", "config")}
        save_model(model, n, out / n, extra=extra, dtype=None if n == "cells" else torch.float16)
        size = (out / n / "model.safetensors").stat().st_size
        print(f"{n}: {sum(p.numel() for p in model.parameters()) / 1e6:.2f} M parameters, {size / 1e6:.1f} MB")
    # Whole: the settings it holds (the code's defaults where there is none yet), every field written.
    write_settings(out / "pipeline.json", **read_settings(out / "pipeline.json"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
