"""Time per mesh of the default settings (2 candidates) against a single candidate.

    python benchmarks/candidates.py [--inputs /work/evalsets/oop/inputs] [--limit 10] [--threads 1]
        [--candidates 1,2] [--weights DIR] [--save results.npz] [--compare results.npz]
    python benchmarks/candidates.py --decode-only [--rounds 3] [--limit 10] [--threads 1] [--candidates 2]

Runs ``Pipeline.generate`` with default settings on ``--limit`` inputs spread evenly over the
folder (sorted by name), each candidate count in turn on the same input before the next input,
so that a change in the machine's load hits every setting alike.  Prints per setting the mean
seconds per mesh (the whole ``generate``) and of its vertex stage, the tokens, and the ratio of
each setting's time to the first one's.

``--decode-only`` times the vertex decoder alone (``models.generate.generate``, default sampling
settings) on each input's K candidates (K: the last of ``--candidates``): decoded as one batch,
decoded one after the other (the same tokens), and the first candidate alone; the three are
interleaved and repeated ``--rounds`` times, and the median of each is kept.

``--save`` writes every result (vertices, faces, chosen seed, candidate fits); ``--compare``
checks that this run's results equal a saved run's (the same inputs, seeds and settings,
e.g. before and after a change of the decoding code).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from fastmesh.params import GenerateParams  # noqa: E402
from fastmesh.pipeline import GenerationError, Pipeline  # noqa: E402
from fastmesh.request import Frame  # noqa: E402
from fastmesh.shapes.io import load_shape  # noqa: E402
from fastmesh.shapes.shape import SUPPORTED_FORMATS  # noqa: E402


def pick_inputs(folder: Path, n: int) -> list[Path]:
    """``n`` files spread evenly over the folder's supported inputs, sorted by name."""
    files = sorted(f for f in folder.iterdir() if f.suffix.lower().lstrip(".") in SUPPORTED_FORMATS)
    if not files:
        raise SystemExit(f"no input in {folder}")
    idx = np.unique(np.linspace(0, len(files) - 1, min(n, len(files))).round().astype(int))
    return [files[i] for i in idx]


def _decode_times(pipe: Pipeline, prefix: list, evidence: list, rounds: int) -> tuple[dict, list[int]]:
    """Median seconds of decoding the candidates (rows of ``prefix``/``evidence``) batched, one after
    the other, and the first alone; and the candidates' token counts."""
    from fastmesh.models.generate import StackedEvidence, generate  # here: the default mode runs on older code too
    k = len(prefix)
    cfg = GenerateParams().sampling(pipe.max_vertices)

    def alone(i):
        return generate(pipe.decoder, prefix[i], GenerateParams(seed=cfg.seed + i).sampling(pipe.max_vertices),
                        evidence=evidence[i])[0]

    runs = {"batched": lambda: generate(pipe.decoder, torch.cat(prefix), cfg, evidence=StackedEvidence(evidence)),
            "sequential": lambda: [alone(i) for i in range(k)],
            "first alone": lambda: [alone(0)]}
    times: dict[str, list[float]] = {name: [] for name in runs}
    for _ in range(rounds):  # interleaved, so that a change of load hits all three alike
        for name, fn in runs.items():
            t = time.perf_counter()
            seqs = fn()
            times[name].append(time.perf_counter() - t)
            if name == "sequential":
                lengths = [len(s) for s in seqs]
    return {name: float(np.median(v)) for name, v in times.items()}, lengths


def time_decoding(pipe: Pipeline, inputs: list[Path], k: int, rounds: int) -> None:
    """Vertex decoding of k candidates per input: batched, sequential and the first alone (medians)."""
    totals = {"batched": 0.0, "sequential": 0.0, "first alone": 0.0}
    for f in inputs:
        shape = load_shape(f)
        # Candidate k's own surface sample and condition, as Pipeline.generate makes them.
        frame = Frame.of(shape)
        cells = pipe._logodds(frame)
        encoded = [pipe._encode(frame, seed, GenerateParams(), cells) for seed in range(k)]
        prefix, evidence = [e[2] for e in encoded], [e[3] for e in encoded]
        med, lengths = _decode_times(pipe, prefix, evidence, rounds)
        for name in totals:
            totals[name] += med[name]
        print(f"{f.name[:60]}: tokens {lengths} | " + " | ".join(f"{n} {v:.2f} s" for n, v in med.items()), flush=True)
    print(f"\n{len(inputs)} inputs, {k} candidates, median of {rounds} rounds, summed: "
          + ", ".join(f"{n} {v:.1f} s" for n, v in totals.items())
          + f"; batched / first alone x{totals['batched'] / totals['first alone']:.2f}, "
          f"sequential / first alone x{totals['sequential'] / totals['first alone']:.2f}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--inputs", default="/work/evalsets/oop/inputs", type=Path)
    ap.add_argument("--limit", type=int, default=10)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--candidates", default="1,2", help="comma-separated candidate counts")
    ap.add_argument("--weights", default=None, metavar="DIR")
    ap.add_argument("--save", type=Path, default=None)
    ap.add_argument("--compare", type=Path, default=None)
    ap.add_argument("--decode-only", action="store_true", help="time the vertex decoding alone (see above)")
    ap.add_argument("--rounds", type=int, default=3)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    try:
        pipe = Pipeline.from_pretrained(args.weights, device="cpu", threads=args.threads)
    except TypeError:  # code from before Pipeline took a thread count: torch's, set above
        pipe = Pipeline.from_pretrained(args.weights, device="cpu")
    counts = [int(c) for c in args.candidates.split(",")]
    inputs = pick_inputs(args.inputs, args.limit)
    if args.decode_only:
        time_decoding(pipe, inputs, counts[-1], args.rounds)
        return 0
    pipe.generate(load_shape(inputs[0]), GenerateParams(max_vertices=8))  # warm up
    secs = {c: [] for c in counts}
    vert_secs = {c: [] for c in counts}
    tokens = {c: [] for c in counts}
    saved: dict[str, np.ndarray] = {}
    for f in inputs:
        shape = load_shape(f)
        line = [f.name[:60]]
        for c in counts:
            t = time.perf_counter()
            try:
                res = pipe.generate(shape, GenerateParams(candidates=c))
            except GenerationError as e:
                line.append(f"c={c}: failed ({e.code})")
                continue
            secs[c].append(time.perf_counter() - t)
            vert_secs[c].append(res.timings["vertices"])
            tokens[c].append(res.tokens)
            key = f"{f.name}/{c}"
            saved.update({f"{key}/vertices": res.vertices, f"{key}/faces": res.faces,
                          f"{key}/chosen_seed": np.array(res.info["chosen_seed"]),
                          f"{key}/fits": np.array(res.info.get("fits", []), dtype=float)})
            line.append(f"c={c}: {secs[c][-1]:.2f} s (vertices {res.timings['vertices']:.2f} s, "
                        f"{res.info['generated_vertices']} V)")
        print(" | ".join(line), flush=True)
    print(f"\nweights {pipe.source}, decoder {pipe.info()['decoder']}, {args.threads} thread(s), "
          f"{len(inputs)} inputs of {args.inputs}")
    first = counts[0]
    for c in counts:
        if not secs[c]:
            continue
        print(f"candidates={c}: {np.mean(secs[c]):.2f} s per mesh (vertex stage {np.mean(vert_secs[c]):.2f} s), "
              f"{len(secs[c])} meshes; x{np.sum(secs[c]) / np.sum(secs[first]):.2f} the time of candidates={first}")
    if args.save:
        np.savez(args.save, **saved)
    if args.compare:
        ref = np.load(args.compare)
        common = sorted(set(ref.files) & set(saved))
        differ = sorted({k.rsplit("/", 1)[0] for k in common if not np.array_equal(ref[k], saved[k])})
        print(f"compared with {args.compare}: {len(common) // 4} results in both, {len(differ)} differ"
              + (f": {', '.join(differ)}" if differ else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
