"""The evaluation's measures of what a renderer shows (:mod:`.visible`, :mod:`.defects`), per result and summed up
over a run, and the contact sheets beside them.

Per result (a system's row of :func:`fastmesh.evaluation.eval.evaluate_end_to_end`)::

    back_face_share, silhouette_iou, normal_angle   :func:`.visible.visible_report` against the reference
    misoriented_edges, misoriented_area, self_intersections, unwelded_vertices   :func:`.defects.defects`
    unwelded_share            unwelded_vertices / the result's referenced vertices
    faces_per_reference_face  the result's faces / the reference's

The reference's own back_face_share and defects go into its row, since some artist meshes are single-sided
or wound inside out.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..faces.defects import defects
from .visible import Views, back_face_share, cameras, normal_angle, render_views, silhouette_iou

OVER_REFERENCE = 0.05  # a result showing more than 5 points more back faces than its reference counts as over


def reference_sight(vertices: np.ndarray, faces: np.ndarray) -> tuple[list, Views, dict]:
    """The cameras fitted to a reference (V, 3) / (F, 3), its views and its own figures (back_face_share and
    :func:`.defects.defects`)."""
    cams = cameras(vertices)
    views = render_views(vertices, faces, cams)
    return cams, views, {"back_face_share": back_face_share(views), **defects(vertices, faces)}


def score_sight(vertices: np.ndarray, faces: np.ndarray, cams: list, ref_views: Views, ref_faces: int) -> dict:
    """A result's figures (module docstring) through the reference's cameras ``cams`` and views ``ref_views``."""
    mine = render_views(vertices, faces, cams)
    bad = defects(vertices, faces)
    used = max(1, len(np.unique(np.asarray(faces, dtype=np.int64))))
    return {"back_face_share": back_face_share(mine), "silhouette_iou": silhouette_iou(mine, ref_views),
            "normal_angle": normal_angle(mine, ref_views), **bad,
            "unwelded_share": bad["unwelded_vertices"] / used,
            "faces_per_reference_face": len(faces) / max(1, ref_faces)}


def summarise_sight(rows: list[dict], system: str) -> dict:
    """Over the rows where ``system`` made a result with these figures: means of the figures, the references'
    mean back-face share on the same rows, and counts of results over their reference by more than
    ``OVER_REFERENCE``, with any misoriented edge, with any crossing and with any unwelded vertex."""
    ok = [r for r in rows if "back_face_share" in r.get(system, {})]
    if not ok:
        return {}
    mine = [r[system] for r in ok]
    ref = [r["reference"].get("back_face_share", np.nan) for r in ok]
    out = {f"mean_{k}": float(np.nanmean([m[k] for m in mine]))
           for k in ("back_face_share", "silhouette_iou", "normal_angle", "misoriented_area", "unwelded_share",
                     "faces_per_reference_face")}
    out["mean_reference_back_face_share"] = float(np.nanmean(ref))
    out["over_reference_back_faces"] = int(sum(m["back_face_share"] - b > OVER_REFERENCE
                                               for m, b in zip(mine, ref, strict=True)))
    out["with_misoriented_edges"] = int(sum(m["misoriented_edges"] > 0 for m in mine))
    out["with_self_intersections"] = int(sum(m["self_intersections"] > 0 for m in mine))
    out["with_unwelded_vertices"] = int(sum(m["unwelded_vertices"] > 0 for m in mine))
    return out


def write_sheet(folder: str | Path, name: str, meshes: list[tuple[np.ndarray, np.ndarray] | None],
                size: int = 256) -> Path:
    """``folder/<name>.png``: :func:`fastmesh.preview.sheet.contact_sheet` of ``meshes`` (rows in order)."""
    from ..preview.png import to_png
    from ..preview.sheet import contact_sheet

    path = Path(folder) / f"{name}.png"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(to_png(contact_sheet(meshes, size=size)))
    return path
