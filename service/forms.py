"""Turning a submission's form fields and file into validated generation parameters and input facts."""

from __future__ import annotations

import dataclasses
import math
import re
import unicodedata

from fastmesh.io import EXPORT_FORMATS, Shape

from .errors import ApiError


def generation_defaults() -> dict:
    """The pipeline's own defaults (shown in the OpenAPI description and used for omitted fields)."""
    from fastmesh.params import GenerateParams

    return dataclasses.asdict(GenerateParams())


def build_params(values: dict, formats: str | None, default_formats: list[str], limit: int | None = None) -> dict:
    """Validate the generation parameters with the pipeline's own rules; add the export formats.

    ``limit`` is the largest ``max_vertices`` the workers' model accepts, when known.

    Raises
    ------
    ApiError
        422 ``invalid_parameter`` naming the field.
    """
    from fastmesh.params import GenerateParams

    given = {k: v for k, v in values.items() if v is not None}
    for k, v in given.items():
        if isinstance(v, float) and not math.isfinite(v):
            raise ApiError(422, "invalid_parameter", f"{k}: must be a finite number")
    try:
        gp = GenerateParams(**given)
        gp.validate() if limit is None else gp.validate(limit=limit)
    except (TypeError, ValueError) as e:
        raise ApiError(422, "invalid_parameter", str(e)) from None
    out = dataclasses.asdict(gp)
    out["formats"] = parse_formats(formats, default_formats)
    return out


def parse_formats(formats: str | None, default: list[str]) -> list[str]:
    if formats is None or not formats.strip():
        return list(default)
    out = []
    for f in formats.split(","):
        f = f.strip().lower().lstrip(".")
        if f not in EXPORT_FORMATS:
            raise ApiError(422, "invalid_parameter",
                           f"formats: unknown format '{f[:20]}'; use a comma list of {', '.join(EXPORT_FORMATS)}")
        if f not in out:
            out.append(f)
    return out


def safe_filename(name: str | None) -> str:
    """The upload's base name, without directories or control characters, at most 200 characters."""
    name = (name or "").replace("\\", "/").rsplit("/", 1)[-1]
    name = "".join(c for c in name if unicodedata.category(c)[0] != "C").strip().lstrip(".")
    name = re.sub(r"\s+", " ", name)
    if len(name) > 200:  # keep the extension, which names the format
        stem, dot, ext = name.rpartition(".")
        name = (stem[: 190] + dot + ext[:9]) if dot else name[:200]
    return name or "upload"


def input_info(filename: str, shape: Shape) -> dict:
    if shape.faces is None:
        return {"filename": filename, "kind": "points", "points": int(len(shape.vertices)),
                "vertices": None, "faces": None}
    return {"filename": filename, "kind": "mesh", "points": None, "vertices": int(len(shape.vertices)),
            "faces": int(len(shape.faces))}
