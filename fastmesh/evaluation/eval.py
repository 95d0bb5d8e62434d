"""Evaluation exactly as ../shared/EVAL.md: generate from point clouds, compare to references.

Several systems can be scored on the same inputs in one run (the baselines are :mod:`.baselines`):

- ``fastmesh``: the pipeline, end to end;
- ``convex_hull``: the floor any method must beat;
- ``poisson``: screened Poisson reconstruction + quadric decimation to the reference's
  face count (pymeshlab, an optional benchmark extra) — what a user would pick instead;
- ``poisson_ours``: the same decimated to our own result's face count, so that both are compared with as many
  faces (on a big reference ours has far fewer than the reference);
- ``decimation`` (mesh inputs): quadric decimation of the input to our own face count.

``gt_vertices`` mode scores the face stage alone: the reference's own 7-bit vertices go
into the face model and the predicted edges are compared with the true ones.

Every system's result is also scored at the vertex stage (:func:`fastmesh.evaluation.metrics.vertex_metrics`,
under ``vertex_metrics``): its vertices against the artist's, in cells of the 7-bit grid.

A mesh that fails to generate is a failure, counted in ``failure_rate``, never dropped.
"""

from __future__ import annotations

import time
from collections import Counter
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np

from ..faces import mesh_from_adjacency
from ..faces.meshops import edges_from_faces, remove_unreferenced, weld
from ..faces.surface_triangles import restricted_delaunay_mesh
from ..faces.triangles import TriangleConfig
from ..shapes.io import input_surface, load_shape, sample_surface, write_mesh
from ..shapes.shape import SUPPORTED_FORMATS, Normalization, Shape, ShapeError
from ..tokenizer import dequantize, quantize_mesh
from .baselines import convex_hull, decimation, dense_remesh, poisson
from .metrics import box_gap, edge_metrics, mesh_topology, surface_distance, vertex_metrics
from .quality import topology
from .seen import reference_sight, score_sight, summarise_sight, write_sheet

MESH_EXTS = ("ply", "obj", "glb", "gltf", "stl", "off")


def pair_inputs(inputs: str | Path, reference: str | Path) -> list[tuple[Path, Path]]:
    """Match every shape in ``inputs`` with the reference mesh of the same stem in ``reference``."""
    refs: dict[str, Path] = {}
    for f in sorted(Path(reference).rglob("*")):
        if f.is_file() and f.suffix.lower().lstrip(".") in MESH_EXTS:
            refs.setdefault(f.relative_to(reference).with_suffix("").as_posix(), f)
    pairs = []
    for f in sorted(Path(inputs).rglob("*")):
        if f.is_file() and f.suffix.lower().lstrip(".") in SUPPORTED_FORMATS:
            key = f.relative_to(inputs).with_suffix("").as_posix()
            if key in refs:
                pairs.append((f, refs[key]))
    if not pairs:
        raise ValueError(f"no input in {inputs} has a reference of the same name in {reference}")
    return pairs


def artist_vertices(ref: Shape, shape: Shape) -> dict:
    """What a result's vertices are scored against, in the reference's normalised frame.

    Returns
    -------
    dict with ``norm`` (the reference's :class:`Normalization`), ``reference`` (M, 3): the artist's
    vertices as the vertex decoder is trained to emit them (``quantize_mesh``: merged per 7-bit cell,
    at their mean position), and ``surface`` (vertices, faces): the input surface, i.e. the input's own
    triangles, or for a point cloud the reference mesh it was sampled from (``export_eval_set``): the
    distance to the nearest of 8,192 scattered points overstates the distance to the surface by
    about a cell (``(None, None)`` when neither is a mesh: no ``on_surface`` then).
    """
    def is_mesh(s: Shape) -> bool:
        return s.faces is not None and len(s.faces) > 0

    norm = Normalization.fit(ref.vertices)
    unit = norm.apply(ref.vertices)
    artist = quantize_mesh(unit, ref.faces)[2] if is_mesh(ref) else np.unique(unit, axis=0)
    surf = shape if is_mesh(shape) else ref if is_mesh(ref) else None
    surface = (norm.apply(surf.vertices), surf.faces) if surf is not None else (None, None)
    return {"norm": norm, "reference": artist, "surface": surface}


def _score(result: tuple[np.ndarray, np.ndarray], ref: Shape, artist: dict) -> dict:
    """CD and HD as the protocol measures them (each shape in its own box), ``cd_shared`` (both in the
    reference's: the surface alone, whatever either box), ``box_gap`` (``metrics.box_gap``), counts and the
    vertex metrics."""
    d = surface_distance(result, (ref.vertices, ref.faces))
    shared = surface_distance(result, (ref.vertices, ref.faces), frame=artist["norm"])
    vm = vertex_metrics(artist["norm"].apply(result[0]), artist["reference"], *artist["surface"])
    return {"cd": d.cd, "hd": d.hd, "cd_shared": shared.cd, "box_gap": box_gap(result[0], ref.vertices),
            "vertices": int(len(result[0])), "faces": int(len(result[1])), "vertex_metrics": vm}


def evaluate_end_to_end(pipe, pairs: list[tuple[Path, Path]], params, systems=("fastmesh",),
                        log: Callable[[str], None] | None = None, save: str | Path | None = None,
                        sheets: str | Path | None = None) -> dict:
    """Score each system on every (input, reference) pair; returns per-mesh rows and summaries.

    Every result is also scored by what a renderer shows (:mod:`.seen`, through cameras fitted to the
    reference, whose own figures go into the row's ``reference``).  With ``save`` every result is written in
    the input's (= the reference's) frame (see :func:`_save`); with ``sheets`` a contact sheet per shape,
    ``sheets/<name>.png`` (:func:`.seen.write_sheet`): rows reference, ours (``fastmesh``) and
    ``poisson_ours`` (grey where a system failed or did not run).
    """
    rows = []
    for i, (inp, ref_path) in enumerate(pairs, 1):
        ref = load_shape(ref_path)
        row, made = _evaluate_pair(pipe, inp.stem, load_shape(inp), ref, params, systems, save)
        rows.append(row)
        if sheets is not None:
            write_sheet(sheets, inp.stem, [(ref.vertices, ref.faces), made.get("fastmesh"), made.get("poisson_ours")])
        if log:
            log(f"[{i}/{len(pairs)}] {inp.name}: reference back {row['reference']['back_face_share']:.3f}, "
                + ", ".join(f"{s} " + _line(row[s]) for s in systems))
    by_package = {p: {s: _summary([r for r in rows if _package(r["name"]) == p], s) for s in systems}
                  for p in sorted({_package(r["name"]) for r in rows})}
    return {"meshes": rows, "summary": {s: _summary(rows, s) for s in systems}, "by_package": by_package}


def _evaluate_pair(pipe, name: str, shape: Shape, ref: Shape, params, systems, save) -> tuple[dict, dict]:
    """One input's row (its reference's counts and sight, then each system's scores, in ``systems``' order) and
    the meshes the systems made (by system name; a failed one is left out)."""
    ref_top = mesh_topology(ref.vertices, ref.faces)
    row = {"name": name, "reference": {"vertices": int(len(ref.vertices)), "faces": int(len(ref.faces)),
                                       "watertight": ref_top["watertight"], "pieces": ref_top["pieces"]}}
    artist = artist_vertices(ref, shape)
    cams, ref_views, ref_seen = reference_sight(ref.vertices, ref.faces)
    row["reference"].update(ref_seen)
    made = {}
    for system in systems:  # in order: ``poisson_ours`` and ``decimation`` read our result's face count from the row
        row[system] = _run_system(pipe, system, name, shape, ref, row, artist, (cams, ref_views), params, save, made)
    return row, made


def _run_system(pipe, system: str, name: str, shape: Shape, ref: Shape, row: dict, artist: dict, sight: tuple,
                params, save: str | Path | None, made: dict) -> dict:
    """One system's scores on one input, timed, its mesh put in ``made``; a failure (no mesh, a bad shape, a runtime
    error) is a row ``{"failed": True, ...}``, never dropped."""
    from ..models.generate import GenerationError

    t = time.perf_counter()
    try:
        mesh, how = _make(pipe, system, shape, ref, row, params)
        out = {**_score(mesh, ref, artist), **_topology_row(*mesh), **score_sight(*mesh, *sight, len(ref.faces)),
               **how}
        made[system] = mesh
        _save(save, system, name, *mesh)
        out["seconds"] = round(time.perf_counter() - t, 4)
    except (GenerationError, ShapeError, RuntimeError) as e:
        out = {"failed": True, "error": f"{type(e).__name__}: {e}"[:200],
               "seconds": round(time.perf_counter() - t, 4)}
    return out


def _make(pipe, system: str, shape: Shape, ref: Shape, row: dict, params) -> tuple[tuple[np.ndarray, np.ndarray], dict]:
    """The mesh ``system`` makes from ``shape`` and its row's notes on how (the pipeline's tokens, timings, sources)."""
    if system == "fastmesh":
        res = pipe.generate(shape, params)
        how = {"tokens": res.tokens, "timings": {k: round(v, 4) for k, v in res.timings.items()},
               "result_from": res.info["result_from"], "vertices_from": res.info["vertices_from"]}
        return (res.vertices, res.faces), how
    if system == "convex_hull":
        return convex_hull(shape), {}
    if system in ("poisson", "poisson_ours"):
        return poisson(shape, len(ref.faces) if system == "poisson" else _our_faces(row, ref), seed=params.seed), {}
    if system == "decimation":
        return decimation(shape, _our_faces(row, ref)), {}
    raise ValueError(f"unknown system {system!r}")


def _summary(rows: list[dict], system: str) -> dict:
    return {**summarise(rows, system), **summarise_sight(rows, system)}


def _our_faces(row: dict, ref: Shape) -> int:
    """The face count of our result in ``row`` (the reference's where it made none)."""
    return row.get("fastmesh", {}).get("faces") or len(ref.faces)


def _package(name: str) -> str:
    """The Debian package of an eval-set name (``fastmesh data eval-set`` names files package__path)."""
    return name.split("__", 1)[0]


def _line(out: dict) -> str:
    if out.get("failed"):
        return "failed"
    vm = out["vertex_metrics"]
    return (f"CD {out['cd']:.2f} HD {out['hd']:.2f} V {vm['generated']}/{vm['reference']} "
            f"P1 {vm['precision_1']:.2f} R1 {vm['recall_1']:.2f} on-surface {vm.get('on_surface', float('nan')):.2f} "
            f"back {out['back_face_share']:.3f} IoU {out['silhouette_iou']:.3f} angle {out['normal_angle']:.1f} "
            f"misoriented {out['misoriented_edges']} ({out['misoriented_area']:.3f}) crossing "
            f"{out['self_intersections']} unwelded {out['unwelded_vertices']} "
            f"F/ref {out['faces_per_reference_face']:.2f}")


def summarise_vertex_metrics(per_mesh: list[dict]) -> dict:
    """Means of :func:`fastmesh.evaluation.metrics.vertex_metrics` over meshes, and the median count ratio."""
    keys = ("precision_1", "precision_2", "recall_1", "recall_2", "on_surface", "count_ratio")
    out = {f"mean_{k}": float(np.mean([m[k] for m in per_mesh if k in m] or [np.nan])) for k in keys}
    out["median_count_ratio"] = float(np.median([m["count_ratio"] for m in per_mesh]))
    return out


def summarise(rows: list[dict], system: str) -> dict:
    ok = [r for r in rows if not r[system].get("failed")]
    out = {"meshes": len(rows), "failures": len(rows) - len(ok),
           "failure_rate": (len(rows) - len(ok)) / max(1, len(rows))}
    if ok:
        for k in ("cd", "hd", "cd_shared", "box_gap", "vertices", "faces", "seconds"):
            if k in ok[0][system]:  # reports written before a measure was added lack it
                out[f"mean_{k}"] = float(np.mean([r[system][k] for r in ok]))
        ratio = [r[system]["faces"] / max(1, r["reference"]["faces"]) for r in ok]
        out["mean_face_ratio"] = float(np.mean(ratio))
        out["over_1_5x_faces"] = int(sum(x > 1.5 for x in ratio))
        out["share_edge_manifold"] = sum(r[system]["edge_manifold"] for r in ok) / len(rows)
        closed = [r for r in ok if r["reference"]["watertight"]]
        out["share_watertight"] = (sum(r[system]["watertight"] for r in closed) / len(closed)
                                   if closed else float("nan"))
        out["more_pieces_than_reference"] = int(sum(r[system]["pieces"] > r["reference"]["pieces"] for r in ok))
        out["share_pieces_within_reference"] = sum(r[system]["pieces"] <= r["reference"]["pieces"]
                                                   for r in ok) / len(rows)
        out["median_boundary_edges"] = float(np.median([r[system]["boundary_edges"] for r in ok]))
        out["median_boundary_edges_closed_references"] = (
            float(np.median([r[system]["boundary_edges"] for r in closed])) if closed else float("nan"))
        out["vertex_metrics"] = summarise_vertex_metrics([r[system]["vertex_metrics"] for r in ok])
        if "timings" in ok[0][system]:
            out["mean_timings"] = {k: float(np.mean([r[system]["timings"][k] for r in ok]))
                                   for k in ok[0][system]["timings"]}
            out["mean_tokens"] = float(np.mean([r[system]["tokens"] for r in ok]))
        for source in ("result_from", "vertices_from"):  # generated, or the input, its planes, its decimation ...
            if source in ok[0][system]:
                out[source] = dict(sorted(Counter(r[system][source] for r in ok).items()))
    return out


def _save(save: str | Path | None, system: str, name: str, vertices: np.ndarray, faces: np.ndarray) -> None:
    """``save/<name>.ply`` for the pipeline, ``save/<system>/<name>.ply`` for the others."""
    if save is None or len(faces) == 0:
        return
    folder = Path(save) if system == "fastmesh" else Path(save) / system
    folder.mkdir(parents=True, exist_ok=True)
    write_mesh(folder / f"{name}.ply", vertices, faces)


def _topology_row(vertices: np.ndarray, faces: np.ndarray) -> dict:
    t = mesh_topology(vertices, faces)
    return {"edge_manifold": t["edge_manifold"], "watertight": t["watertight"], "pieces": t["pieces"],
            "boundary_edges": topology(weld(vertices, faces)[1])["boundary_edges"]}


def gt_vertex_systems(triangle_config: TriangleConfig, baseline: bool) -> dict[str, TriangleConfig | None]:
    """The face stages ``evaluate_gt_vertices`` scores: the pipeline's (``fastmesh``); with ``baseline``
    also the other selection with the same settings (``selection_cliques`` or ``selection_surface``)
    and the restricted Delaunay anchor (``restricted_delaunay``, no model)."""
    systems: dict[str, TriangleConfig | None] = {"fastmesh": triangle_config}
    if baseline:
        other = "cliques" if triangle_config.selection == "surface" else "surface"
        systems[f"selection_{other}"] = replace(triangle_config, selection=other)
        systems["restricted_delaunay"] = None
    return systems


def evaluate_gt_vertices(pipe, pairs: list[tuple[Path, Path]], filtering: bool = True, seed: int = 0,
                         max_vertices: int | None = None, log: Callable[[str], None] | None = None,
                         baseline: bool = False, save: str | Path | None = None) -> dict:
    """Face stages alone on each reference's own 7-bit vertices, side by side on the same points.

    Per mesh: the model's predicted-edge precision/recall/F1; per system (:func:`gt_vertex_systems`):
    CD, HD, faces, the result's edge precision/recall/F1 against the reference's, edge-manifold,
    watertight, pieces, seconds (the network pass counts for the systems that use it).  With ``save``
    every result is written in the reference's original frame (see :func:`_save`).
    """
    systems = gt_vertex_systems(pipe.triangle_config, baseline)
    rows = []
    for i, (inp, ref_path) in enumerate(pairs, 1):
        ref = load_shape(ref_path)
        shape = load_shape(inp)
        norm = Normalization.fit(ref.vertices)
        q, true_faces, cont = quantize_mesh(norm.apply(ref.vertices), ref.faces)
        if max_vertices and len(q) > max_vertices:
            continue
        # The condition comes from the input shape, in the reference's normalised frame.
        n_fp = pipe.face.cfg.encoder.n_points
        pts, nrm = sample_surface(shape, n_fp, seed=seed, vertices=norm.apply(shape.vertices))
        t = time.perf_counter()
        edges, logits = pipe.face.predict_edges(q, pts, nrm, filtering=pipe.filter_config if filtering else None,
                                                return_logits=True)
        net_seconds = time.perf_counter() - t
        true_edges = edges_from_faces(true_faces)
        m = edge_metrics(edges, true_edges)
        surface = input_surface(shape, norm.apply(shape.vertices), pipe.triangle_config.support_points, seed)
        ref_top = mesh_topology(q, true_faces)
        row = {"name": inp.stem, "vertices": int(len(q)), "true_faces": int(len(true_faces)),
               "reference": {"watertight": ref_top["watertight"], "pieces": ref_top["pieces"]},
               "precision": m["precision"], "recall": m["recall"], "f1": m["f1"]}
        for system, cfg in systems.items():
            t = time.perf_counter()
            v = dequantize(q)
            if cfg is None:
                f = restricted_delaunay_mesh(v, surface)
            else:  # the reference's vertex indices, to compare edges
                f = mesh_from_adjacency(v, edges, replace(cfg, remove_unreferenced=False), points=surface,
                                        logits=logits)[1]
            seconds = time.perf_counter() - t + (0.0 if cfg is None else net_seconds)
            row[system], placed = _gt_result(v, f, seconds, true_edges, norm, ref)
            if placed is not None:
                _save(save, system, inp.stem, *placed)
        rows.append(row)
        if log:
            log(f"[{i}/{len(pairs)}] {inp.name}: V {len(q)} P {m['precision']:.3f} R {m['recall']:.3f} "
                f"F1 {m['f1']:.3f} | " + ", ".join(
                    f"{s} " + ("failed" if row[s].get("failed") else f"CD {row[s]['cd']:.2f} HD {row[s]['hd']:.2f}")
                    for s in systems))
    summary = {"meshes": len(rows)}
    for k in ("precision", "recall", "f1"):
        summary[f"mean_{k}"] = float(np.mean([r[k] for r in rows])) if rows else float("nan")
    for system in systems:
        summary[system] = summarise_gt(rows, system)
    return {"meshes": rows, "summary": summary}


def _gt_result(v: np.ndarray, f: np.ndarray, seconds: float, true_edges: np.ndarray, norm: Normalization,
               ref: Shape) -> tuple[dict, tuple[np.ndarray, np.ndarray] | None]:
    """One system's row of :func:`evaluate_gt_vertices` and its mesh in the reference's frame (None where it
    made no faces).  The row: faces and seconds; where it made faces, CD and HD against the reference, the edge
    precision/recall/F1 of its faces and its topology, else ``failed``."""
    out = {"faces": int(len(f)), "seconds": round(seconds, 4)}
    if not len(f):
        return {**out, "failed": True}, None
    me = edge_metrics(edges_from_faces(f), true_edges)
    v, f, _ = remove_unreferenced(v, f)  # the result's own bounding box normalises it
    d = surface_distance((norm.invert(v), f), (ref.vertices, ref.faces))
    out.update(cd=d.cd, hd=d.hd, edge_precision=me["precision"], edge_recall=me["recall"],
               edge_f1=me["f1"], **_topology_row(v, f))
    return out, (norm.invert(v), f)


def summarise_gt(rows: list[dict], system: str) -> dict:
    """Means over one system's results of :func:`evaluate_gt_vertices` rows (CD/HD over the meshes it
    made), shares edge-manifold (over all meshes) and watertight (over the watertight references)."""
    ok = [r for r in rows if not r[system].get("failed")]
    out = {"meshes": len(rows), "failures": len(rows) - len(ok)}
    for k in ("cd", "hd", "edge_precision", "edge_recall", "edge_f1"):
        out[f"mean_{k}"] = float(np.mean([r[system][k] for r in ok])) if ok else float("nan")
    for k in ("faces", "seconds"):
        out[f"mean_{k}"] = float(np.mean([r[system][k] for r in rows])) if rows else float("nan")
    out["share_edge_manifold"] = sum(r[system].get("edge_manifold", False) for r in rows) / max(1, len(rows))
    closed = [r for r in rows if r["reference"]["watertight"]]
    out["watertight_references"] = len(closed)
    out["share_watertight"] = (sum(r[system].get("watertight", False) for r in closed) / len(closed)
                               if closed else float("nan"))
    out["more_pieces_than_reference"] = sum(r[system].get("pieces", 0) > r["reference"]["pieces"] for r in ok)
    return out


def export_eval_set(ds, source_root: str | Path, out: str | Path, split: str = "val", n_points: int = 8192,
                    seed: int = 0, max_vertices: int | None = None, per_package: int | None = None,
                    dense_faces: int | None = None) -> int:
    """Write ``inputs/<name>.npz`` (points + normals, the reference's frame) and ``reference/<name>.ply``.

    The input point cloud is sampled from the original reference mesh, as a user's scan
    of it would be; returns the number of pairs written.  With ``per_package`` = n, only n
    meshes of each package, evenly spaced in its list, so that a small set still holds every
    package of the split.  With ``dense_faces`` the inputs are meshes instead, ``inputs/<name>.ply``:
    the reference remeshed densely without its structure (:func:`dense_remesh`).
    """
    import shutil

    out = Path(out)
    (out / "inputs").mkdir(parents=True, exist_ok=True)
    (out / "reference").mkdir(parents=True, exist_ok=True)
    chosen = [i for i in ds.indices(split) if not (max_vertices and ds.num_vertices()[i] > max_vertices)]
    if per_package:
        package = ds.arrays["package"]
        subsets = []
        for p in sorted(set(package[chosen])):
            mine = [i for i in chosen if package[i] == p]
            subsets += [mine[j] for j in np.unique(np.linspace(0, len(mine) - 1, per_package).round().astype(int))]
        chosen = sorted(subsets)
    count = 0
    for i in chosen:
        name = str(ds.arrays["name"][i])
        src = Path(source_root) / name
        ref = load_shape(src)
        stem = name.replace("/", "__").rsplit(".", 1)[0]
        if dense_faces:
            write_mesh(out / "inputs" / f"{stem}.ply", *dense_remesh(ref.vertices, ref.faces, dense_faces))
        else:
            pts, nrm = sample_surface(ref, n_points, seed=seed)
            np.savez(out / "inputs" / f"{stem}.npz", points=pts, normals=nrm)
        shutil.copyfile(src, out / "reference" / f"{stem}{src.suffix}")
        count += 1
    return count
