"""What closing and making whole cost a job: seconds of ``Pipeline.generate`` and of its parts, on varied inputs.

    python benchmarks/step8_cost.py [--n 12] [--seed 9] [--root DIR] [--threads 1] [--pairs 3]

Runs ``generate`` on ``tests/gpu_inputs.varied(n, seed)`` (point clouds with and without a face-count
target, artist meshes, posed primitives: made from seeds, nothing to download) and a turned 64-sided cylinder
(generated in two frames), after one warm-up, and times inside each job:

- ``decide``: deciding closedness (``closure.decide_closed``: winding numbers on a point cloud);
- ``frame``: choosing the frame (``canonical.canonical_rotation`` with the normals it reads, and the choice
  between the two frames' results);
- ``second_frame``: the job's time less the same job's made in its own frame only (inputs with two frames;
  medians of ``--pairs`` alternated runs of each, the job's time their median too);
- ``closure``: closing the loops hole filling leaves (``closure.close_loops``);
- ``whole``: making the result whole (``pipeline.result.whole``: pinches, strays, far vertices, a low-poly input);
- ``fit``: fitting the result to the input (``pipeline.result``'s ``redistributed``, ``swapped``, ``decimated``
  and ``extended``: a point cloud's faces spread over it, edges turned, a mesh input's decimation weighed, the
  box brought to the input's; a ``--root`` without one of them times the others);
- ``holes``: the face stage's hole filling (``holes.fill_holes``), reported beside them.

Prints one JSON line: the sums over the jobs, the share of the jobs' time that step 8 (decide, frame,
second_frame, closure, whole, fit) takes, that share with the hole filling added, and the share of closing and
fitting alone (decide, closure, whole, fit) over the rest of the job.  ``--root`` runs another
checkout's ``fastmesh`` (a ``git worktree`` of another commit): alternate the runs, the machine's load drifts.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections import defaultdict
from pathlib import Path

STEP8 = ("decide", "frame", "second_frame", "closure", "whole", "fit")
CLOSE_AND_FIT = ("decide", "closure", "whole", "fit")


def _timed(fn, name: str, spent: dict):
    def run(*args, **kwargs):
        t = time.perf_counter()
        try:
            return fn(*args, **kwargs)
        finally:
            spent[name] += time.perf_counter() - t

    return run


def _wrap_parts(pipeline, surface_triangles, Pipeline, spent: dict) -> dict:
    """Time step 8's parts into ``spent`` by name; returns a counter of the frames each job makes (``n``)."""
    pipeline.decide_closed = _timed(pipeline.decide_closed, "decide", spent)
    for name in ("canonical_rotation", "frame_normals"):
        setattr(pipeline, name, _timed(getattr(pipeline, name), "frame", spent))
    Pipeline._nearest_frame = _timed(Pipeline._nearest_frame, "frame", spent)
    pipeline.step8.whole = _timed(pipeline.step8.whole, "whole", spent)
    for name in ("redistributed", "swapped", "decimated", "extended"):
        if hasattr(pipeline.step8, name):
            setattr(pipeline.step8, name, _timed(getattr(pipeline.step8, name), "fit", spent))
    surface_triangles.close_loops = _timed(surface_triangles.close_loops, "closure", spent)
    surface_triangles.fill_holes = _timed(surface_triangles.fill_holes, "holes", spent)
    frames = {"n": 0}
    make_frame = Pipeline._frame

    def counted(self, *a, **k):
        frames["n"] += 1
        return make_frame(self, *a, **k)

    Pipeline._frame = counted
    return frames


def _with_and_without_turn(pipeline, pipe, shape, params, pairs: int, first: float) -> tuple[float, float]:
    """Median seconds of the job (``first`` and ``pairs`` more runs) and of the job in its own frame only
    (``pairs`` runs), alternated: a difference of two single runs is mostly the machine's drift."""
    import numpy as np

    turn = pipeline.canonical_rotation
    both, alone = [first], []
    for _ in range(pairs):
        pipeline.canonical_rotation = lambda *a, **k: np.eye(3)
        t = time.perf_counter()
        pipe.generate(shape, params)
        alone.append(time.perf_counter() - t)
        pipeline.canonical_rotation = turn
        t = time.perf_counter()
        pipe.generate(shape, params)
        both.append(time.perf_counter() - t)
    return float(np.median(both)), float(np.median(alone))


def _inputs(n: int, seed: int) -> list:
    import numpy as np
    import trimesh
    from gpu_inputs import varied

    from fastmesh.evaluation.primitives import posed
    from fastmesh.params import GenerateParams
    from fastmesh.shapes.shape import Shape

    cylinder = trimesh.creation.cylinder(0.3, 0.8, sections=64)
    turned = posed(Shape(vertices=np.asarray(cylinder.vertices), faces=np.asarray(cylinder.faces)),
                   np.random.default_rng(7))
    return [*varied(n, seed=seed), ("cylinder64-turned", turned, GenerateParams(seed=2))]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, default=12, help="varied inputs")
    ap.add_argument("--seed", type=int, default=9)
    ap.add_argument("--root", default=str(Path(__file__).resolve().parents[1]), metavar="DIR",
                    help="the checkout whose fastmesh runs (default: this one)")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--pairs", type=int, default=3, help="runs with and without the second frame, alternated")
    args = ap.parse_args()
    sys.path[:0] = [args.root, str(Path(args.root) / "tests")]
    import numpy as np

    from fastmesh import pipeline
    from fastmesh.faces import surface_triangles
    from fastmesh.pipeline import Pipeline

    spent: dict[str, float] = defaultdict(float)
    frames = _wrap_parts(pipeline, surface_triangles, Pipeline, spent)
    pipe = Pipeline.from_pretrained(threads=args.threads)
    items = _inputs(args.n, args.seed)
    pipe.generate(items[0][1], items[0][2])  # warm-up: first-call costs are not the pipeline's
    spent.clear()
    jobs = {}
    for name, shape, params in items:
        frames["n"] = 0
        t = time.perf_counter()
        pipe.generate(shape, params)
        jobs[name] = time.perf_counter() - t
        if frames["n"] > 1:  # what the second frame adds
            before = dict(spent)
            jobs[name], alone = _with_and_without_turn(pipeline, pipe, shape, params, args.pairs, jobs[name])
            spent.clear()
            spent.update(before)
            spent["second_frame"] += jobs[name] - alone
    total = sum(jobs.values())
    step8 = sum(spent[k] for k in STEP8)
    close_fit = sum(spent[k] for k in CLOSE_AND_FIT)
    print(json.dumps({"root": args.root, "jobs": len(jobs), "seconds": round(total, 3),
                      "median": round(float(np.median(list(jobs.values()))), 3),
                      "parts": {k: round(spent[k], 3) for k in (*STEP8, "holes")},
                      "step8_share": round(step8 / total, 4),
                      "step8_share_of_the_rest": round(step8 / (total - step8), 4),
                      "close_and_fit_share_of_the_rest": round(close_fit / (total - close_fit), 4),
                      "with_holes_share_of_the_rest": round((step8 + spent["holes"]) / (total - step8 - spent["holes"]),
                                                            4),
                      "runs": {k: round(v, 3) for k, v in jobs.items()}}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
