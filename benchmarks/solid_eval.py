"""The pipeline with the solid face stage (``TriangleConfig.solid``) set several ways, on held-out shapes.

Usage: OMP_NUM_THREADS=1 nice python benchmarks/solid_eval.py [--data data/eval-oop] [--n 15] [--seed 0]
       [--margins none,1.1,1.1:closedonly,1.1:nopatch] [--closed-only] [--part i/k] [--out /tmp/solid_eval.json]
       [--sheets DIR]

A random ``n`` of the set's (input, reference) pairs (``seed``), each generated once per setting: ``none``, the
solid stage off; ``inf``, its mesh always comes back; a number, where its surface fit is at most that many times
the selection's (what ships: 1.1).  Flags after it: ``:nopatch``, no part of the selection patched in where the
cut lost one (``TriangleConfig.solid_patch`` off); ``:noflat``, the solid's flat vertices kept; ``:closedonly``,
inputs decided open do not get the stage (``TriangleConfig.solid_open`` off).  ``--closed-only`` leaves out the
inputs decided open; ``--part i/k`` runs every k-th pair from the i-th (halves side by side).  Per result: CD and
HD against the reference (``evaluation.metrics``), watertight, faces wound against their neighbours and
self-intersecting faces (``faces.defects``), the back-face share, silhouette overlap and normal angle over 14 views
(``evaluation.visible``), seconds, faces, which face stage came back, and the solid's rival faces patched in and
thin-part vertices added (``solid.solid_mesh``).  ``--sheets`` writes one PNG per shape: the reference, then each
setting's result (front and back 3/4 views with back faces in red, and a wireframe).
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace
from pathlib import Path

import numpy as np


def margin_of(text: str) -> tuple[float | None, set[str]]:
    """A ``--margins`` token: ``none``, a number, ``inf``; then flags: ``:nopatch``, ``:noflat``, ``:closedonly``."""
    value, *flags = text.split(":")
    return (None if value == "none" else float(value)), set(flags)


def score(vertices: np.ndarray, faces: np.ndarray, ref) -> dict:
    from fastmesh.evaluation.metrics import mesh_topology, surface_distance
    from fastmesh.evaluation.visible import visible_report
    from fastmesh.faces.defects import defects

    d = surface_distance((vertices, faces), (ref.vertices, ref.faces))
    out = {"cd": d.cd, "hd": d.hd, "faces": int(len(faces)),
           "watertight": bool(mesh_topology(vertices, faces)["watertight"])}
    out.update(defects(vertices, faces))
    out.update(visible_report(vertices, faces, (ref.vertices, ref.faces)))
    return out


def summary(rows: list[dict], key: str) -> dict:
    ok = [r[key] for r in rows if key in r]
    mean = {m: round(float(np.mean([o[m] for o in ok])), 4)
            for m in ("cd", "hd", "back_face_share", "silhouette_iou", "normal_angle", "misoriented_area", "seconds")}
    return {"n": len(ok), **mean, "watertight": sum(o["watertight"] for o in ok),
            "any_misoriented": sum(o["misoriented_edges"] > 0 for o in ok),
            "any_self_intersecting": sum(o["self_intersections"] > 0 for o in ok),
            "solid_came_back": sum(o.get("faces_from") == "solid" for o in ok)}


def main() -> None:
    import torch

    from fastmesh.evaluation.eval import pair_inputs
    from fastmesh.faces import solid as solid_module
    from fastmesh.params import GenerateParams
    from fastmesh.pipeline import Pipeline
    from fastmesh.shapes.io import load_shape

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=Path("data/eval-oop"))
    ap.add_argument("--n", type=int, default=15)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--margins", default="none,1.1,1.1:closedonly")
    ap.add_argument("--out", type=Path, default=Path("/tmp/solid_eval.json"))
    ap.add_argument("--sheets", type=Path, default=None)
    ap.add_argument("--closed-only", action="store_true", help="leave out inputs decided open")
    ap.add_argument("--part", default="0/1", help="i/k: every k-th of the picked pairs from the i-th")
    args = ap.parse_args()
    torch.set_num_threads(1)
    pairs = pair_inputs(args.data / "inputs", args.data / "reference")
    pick = np.sort(np.random.default_rng(args.seed).choice(len(pairs), min(args.n, len(pairs)), replace=False))
    part, parts = (int(x) for x in args.part.split("/"))
    pick = pick[part::parts]
    pipe = Pipeline.from_pretrained(device="cpu")
    shipped = pipe.triangle_config
    without_flat = solid_module._without_flat
    margins = args.margins.split(",")
    rows = []
    for i in pick:
        inp, ref_path = pairs[i]
        ref = load_shape(ref_path)
        shape = load_shape(inp)
        row, meshes = {"name": inp.stem}, [(ref.vertices, ref.faces)]
        for m in margins:
            if m != margins[0] and args.closed_only and not row[margins[0]]["closed_decision"]["close"]:
                break
            margin, flags = margin_of(m)
            pipe.triangle_config = replace(shipped, solid=margin, solid_patch="nopatch" not in flags,
                                           solid_open="closedonly" not in flags)
            solid_module._without_flat = (lambda v, f, tol: (v, f)) if "noflat" in flags else without_flat
            t = time.perf_counter()
            res = pipe.generate(shape, GenerateParams(seed=0))
            seconds = time.perf_counter() - t
            solid = res.info.get("solid_fits", {})
            row[m] = {**score(res.vertices, res.faces, ref), "seconds": round(seconds, 3),
                      "faces_from": solid.get("faces_from"), "fits": solid.get("fits"),
                      "patched_faces": solid.get("patched_faces"), "thin_vertices": solid.get("thin_vertices"),
                      "closed_decision": res.info.get("closed_decision")}
            meshes.append((res.vertices, res.faces))
        if len(row) < len(margins) + 1:
            continue
        rows.append(row)
        print(inp.stem[:60], " | ".join(f"{m}: cd {row[m]['cd']:.2f} hd {row[m]['hd']:.2f} "
                                        f"back {row[m]['back_face_share']:.3f} wt {int(row[m]['watertight'])} "
                                        f"mis {row[m]['misoriented_edges']} si {row[m]['self_intersections']} "
                                        f"{row[m]['faces_from']}" for m in margins), flush=True)
        if args.sheets is not None:
            from fastmesh.preview.png import to_png
            from fastmesh.preview.sheet import contact_sheet

            args.sheets.mkdir(parents=True, exist_ok=True)
            (args.sheets / f"{inp.stem[:80]}.png").write_bytes(to_png(contact_sheet(meshes, size=200)))
    out = {"margins": margins, "meshes": rows, "summary": {m: summary(rows, m) for m in margins}}
    args.out.write_text(json.dumps(out, indent=1, default=float))
    print(json.dumps(out["summary"], indent=1))


if __name__ == "__main__":
    main()
