"""Vertex-decoder speed: per-token latency vs a matrix-vector bound, and FastMesh vs BPT length.

    python benchmarks/decode.py [--weights DIR] [--data data/corpus-1k.npz] [--meshes 20] [--threads 1]

1. Per-token latency of the decoder with its KV cache (batch 1, fp32), against the
   *matrix-vector bound*: the time of the bare matrix-vector products with the same
   weight matrices (every Linear of every layer plus the output head), i.e. the work
   no implementation of this network can skip.
2. For validation meshes: the FastMesh sequence length and the BPT sequence length of
   the same quantised mesh, and the measured time of the same decoder producing
   sequences of each length (forced lengths; same cache, same code path).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from fastmesh.data import load_dataset  # noqa: E402
from fastmesh.models.kv_cache import KVCache  # noqa: E402
from fastmesh.pipeline import Pipeline  # noqa: E402
from fastmesh.tokenizer import bpt  # noqa: E402
from fastmesh.tokenizer import vertex as vt  # noqa: E402


@torch.inference_mode()
def time_decode(model, prefix: torch.Tensor, n_tokens: int) -> float:
    """Seconds to prefill and then decode exactly ``n_tokens`` tokens (greedy, grammar not enforced)."""
    cfg = model.cfg
    m = prefix.shape[1]
    cache = KVCache(cfg.depth, 1, cfg.heads, m + n_tokens + 1, cfg.head_dim)
    t = time.perf_counter()
    tok = torch.full((1, 1), vt.BOS, dtype=torch.long)
    logits = model.prefill(prefix, tok, cache)
    block = torch.zeros((1, 1), dtype=torch.long)
    for step in range(1, n_tokens):
        tok = logits.argmax(-1, keepdim=True)
        logits = model.decode_step(tok, block, m + step, cache)
    return time.perf_counter() - t


@torch.inference_mode()
def matvec_bound(model, repeats: int = 50) -> float:
    """Seconds per token of y = W x over every decoder Linear weight and the head."""
    mats = [mod.weight for name, mod in model.named_modules()
            if isinstance(mod, torch.nn.Linear) and not name.startswith(("encoder", "cond_proj"))]
    xs = [torch.randn(w.shape[1]) for w in mats]
    for w, x in zip(mats, xs, strict=True):  # warm up
        torch.mv(w, x)
    t = time.perf_counter()
    for _ in range(repeats):
        for w, x in zip(mats, xs, strict=True):
            torch.mv(w, x)
    return (time.perf_counter() - t) / repeats


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--weights", default=None)
    ap.add_argument("--data", default="data/corpus-1k.npz")
    ap.add_argument("--meshes", type=int, default=20)
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    pipe = Pipeline.from_pretrained(args.weights, device="cpu")
    model = pipe.vertex
    n_par = sum(p.numel() for n, p in model.named_parameters() if not n.startswith("encoder"))
    enc = model.cfg.encoder
    pts = torch.rand(1, enc.n_points, 3) - 0.5
    nrm = torch.nn.functional.normalize(torch.randn(1, enc.n_points, 3), dim=-1)
    with torch.inference_mode():
        prefix = model.condition(pts, nrm)
    time_decode(model, prefix, 32)  # warm up
    n = 400
    per_tok = time_decode(model, prefix, n) / n
    bound = matvec_bound(model)
    print(f"decoder: {n_par / 1e6:.2f} M parameters (without the point encoder), threads={args.threads}")
    print(f"per-token latency (KV cache, {n} tokens): {per_tok * 1e3:.2f} ms")
    print(f"matrix-vector bound: {bound * 1e3:.2f} ms/token  -> ratio {per_tok / bound:.2f}x")

    if not Path(args.data).exists():
        print(f"(no {args.data}: skipping the BPT comparison)")
        return 0
    ds = load_dataset(args.data)
    idx = ds.indices("val")
    rng = np.random.default_rng(0)
    idx = rng.choice(idx, size=min(args.meshes, len(idx)), replace=False)
    rows = []
    for i in idx:
        rec = ds[int(i)]
        l_fm = vt.num_tokens(rec.q)
        l_bpt = bpt.num_tokens(rec.q, rec.faces)
        t_fm = time_decode(model, prefix, l_fm)
        t_bpt = time_decode(model, prefix, l_bpt)
        rows.append((len(rec.q), l_fm, l_bpt, t_fm, t_bpt))
    v, lf, lb, tf, tb = (np.array(c, dtype=float) for c in zip(*rows, strict=True))
    print(f"\n{len(rows)} validation meshes (mean {v.mean():.0f} vertices):")
    print(f"  tokens  fastmesh {lf.mean():.0f}  bpt {lb.mean():.0f}  ratio {lf.sum() / lb.sum():.3f}")
    print(f"  seconds fastmesh {tf.mean():.2f}  bpt {tb.mean():.2f}  speed-up {tb.sum() / tf.sum():.2f}x "
          f"(median per mesh {statistics.median(tb / tf):.2f}x)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
