"""Vertex-decoder speed: per-token latency vs a matrix-vector bound, and FastMesh vs BPT length.

    python benchmarks/decode.py [--weights DIR] [--data data/corpus-1k.npz] [--meshes 20] [--threads 1]
                                [--backend torch|onnx|both]

1. Per-token latency of the decoder with its KV cache (batch 1, fp32), against the
   *matrix-vector bound*: the time of the bare matrix-vector products with the same
   weight matrices (every Linear of every layer plus the output head), i.e. the work
   no implementation of this network can skip.  Backends: eager PyTorch and the ONNX
   Runtime decode step (``models.onnx_decode``), timed interleaved in the same run so
   a busy machine slows both alike.
2. The real ``generate()`` loop (grammar mask, evidence bias, sampling at the shipped
   settings) on the point clouds of validation meshes: ms per token, and its cost per token
   beyond the bare decode steps of the same length.
3. For validation meshes: the FastMesh sequence length and the BPT sequence length of
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

from fastmesh.models.generate import generate  # noqa: E402
from fastmesh.models.kv_cache import KVCache  # noqa: E402
from fastmesh.params import GenerateParams  # noqa: E402
from fastmesh.pipeline import Pipeline  # noqa: E402
from fastmesh.shapes.io import sample_triangles  # noqa: E402
from fastmesh.tokenizer import bpt  # noqa: E402
from fastmesh.tokenizer import vertex as vt  # noqa: E402
from fastmesh.training.data import load_dataset  # noqa: E402


@torch.inference_mode()
def time_decode(model, prefix: torch.Tensor, n_tokens: int) -> float:
    """Seconds to prefill and then decode exactly ``n_tokens`` tokens (greedy, grammar not enforced).

    ``model`` is a ``VertexDecoder`` or an ``OrtDecoder`` (which brings its own cache).
    """
    cfg = model.cfg
    m = prefix.shape[1]
    if hasattr(model, "new_cache"):
        cache = model.new_cache(1, m + n_tokens + 1, "cpu", torch.float32)
    else:
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


def time_generate(pipe: Pipeline, dec, rec, seed: int = 0) -> tuple[int, float, torch.Tensor]:
    """(tokens, seconds, prefix) of the real sampling loop on a validation mesh's point cloud."""
    v = rec.continuous
    pts, nrm = sample_triangles(v, rec.faces, pipe.vertex.cfg.encoder.n_points, np.random.default_rng(seed))
    pts_t, nrm_t = torch.from_numpy(pts)[None], torch.from_numpy(nrm)[None]
    cells = None
    if pipe.vertex.cfg.evidence_cells:  # the cell network reads its own, larger sample
        c_pts, c_nrm = sample_triangles(v, rec.faces, pipe.cell_net.cfg.n_points, np.random.default_rng(seed))
        cells = pipe.cell_net.grid(c_pts, c_nrm)[None]
    with torch.inference_mode():
        prefix = pipe.vertex.condition(pts_t, nrm_t)
        evidence = pipe.vertex.point_evidence(pts_t, nrm_t, cells)
    cfg = GenerateParams(seed=seed).sampling(pipe.max_vertices)
    t = time.perf_counter()
    out = generate(dec, prefix, cfg, evidence=evidence)
    return len(out[0]), time.perf_counter() - t, prefix


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--weights", default=None)
    ap.add_argument("--data", default="data/corpus-1k.npz")
    ap.add_argument("--meshes", type=int, default=20)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--backend", choices=("torch", "onnx", "both"), default="both")
    ap.add_argument("--tokens", type=int, default=400, help="tokens per latency measurement")
    ap.add_argument("--rounds", type=int, default=5, help="interleaved repetitions (the median is reported)")
    ap.add_argument("--gen-meshes", type=int, default=8, help="validation point clouds for the generate() loop")
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
    backends = {}
    if args.backend in ("torch", "both"):
        backends["torch"] = model
    if args.backend in ("onnx", "both"):
        from fastmesh.models.onnx_decode import OrtDecoder

        t = time.perf_counter()
        backends["onnx"] = OrtDecoder(model)
        print(f"onnx export + session: {time.perf_counter() - t:.2f} s")
    n = args.tokens
    times: dict[str, list[float]] = {k: [] for k in backends}
    for dec in backends.values():
        time_decode(dec, prefix, 32)  # warm up
    bounds = []
    for _ in range(args.rounds):  # interleaved (the bound too), so load changes hit everything alike
        bounds.append(matvec_bound(model))
        for name, dec in backends.items():
            times[name].append(time_decode(dec, prefix, n) / n)
    bound = statistics.median(bounds)
    print(f"decoder: {n_par / 1e6:.2f} M parameters (without the point encoder), threads={args.threads}")
    print(f"matrix-vector bound: {bound * 1e3:.2f} ms/token")
    per_tok = {}
    for name in backends:
        per_tok[name] = statistics.median(times[name])
        print(f"{name:>5}: per-token latency (KV cache, {n} tokens, median of {args.rounds}): "
              f"{per_tok[name] * 1e3:.2f} ms  -> ratio {per_tok[name] / bound:.2f}x the bound")
    if Path(args.data).exists():  # the real loop on validation point clouds
        ds = load_dataset(args.data)
        val = np.random.default_rng(1).choice(ds.indices("val"), size=args.gen_meshes, replace=False)
        for name, dec in backends.items():
            n_tok, t_gen, t_bare = 0, 0.0, 0.0
            for i in val:
                k, secs, prefix_i = time_generate(pipe, dec, ds[int(i)])
                n_tok, t_gen, t_bare = n_tok + k, t_gen + secs, t_bare + time_decode(dec, prefix_i, k)
            print(f"{name:>5}: generate() on {len(val)} validation point clouds (T={GenerateParams().temperature}, "
                  f"top-k/top-p, evidence), {n_tok} tokens: {t_gen / n_tok * 1e3:.2f} ms/token, of which "
                  f"{(t_gen - t_bare) / n_tok * 1e3:.2f} ms beyond the bare decode steps")
    if len(per_tok) == 2:
        print(f"onnx speed-up over torch: {per_tok['torch'] / per_tok['onnx']:.2f}x per token (same run)")
    model = backends["onnx" if "onnx" in backends else "torch"]

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
