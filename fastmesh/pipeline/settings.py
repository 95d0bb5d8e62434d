"""A weights folder: the networks' folders and ``pipeline.json``, the settings of the face stage and the fit.

``pipeline.json`` holds every section :func:`read_settings` reads, whole ("filtering": :class:`FilterConfig`,
"faces": :class:`TriangleConfig`, "fit": :class:`FitConfig`); the shipped one equals the code's defaults, so
what ships is what the defaults build.  The decoder's sampling defaults live in :mod:`fastmesh.params`.
"""

from __future__ import annotations

import json
import os
from dataclasses import asdict
from pathlib import Path

from ..faces.filtering import FilterConfig
from ..faces.triangles import TriangleConfig
from ..fitting import FitConfig

NETWORKS = ("vertex", "enhancer", "face")
CELL_NET_DIR = "cells"  # weights folder of the cell network (models.cells.CellNet), for decoders that read it
SECTIONS = {"filtering": FilterConfig, "faces": TriangleConfig, "fit": FitConfig}  # pipeline.json's sections
KEYWORDS = {"filtering": "filter_config", "faces": "triangle_config", "fit": "fit_config"}  # Pipeline's arguments


def default_weights_dir() -> Path:
    """The weights shipped inside the package (``fastmesh/weights``), or ``$FASTMESH_WEIGHTS``."""
    env = os.environ.get("FASTMESH_WEIGHTS")
    return Path(env) if env else Path(__file__).parents[1] / "weights"



def read_settings(path: str | os.PathLike) -> dict:
    """``pipeline.json`` at ``path`` as :class:`fastmesh.pipeline.Pipeline`'s keyword arguments
    (filter_config, triangle_config, fit_config); a section it lacks, or a missing file, gives the defaults.
    A key no config has is an error, not ignored."""
    path = Path(path)
    found = json.loads(path.read_text()) if path.exists() else {}
    unknown = set(found) - set(SECTIONS)
    if unknown:
        raise ValueError(f"{path}: unknown sections {sorted(unknown)} (known: {', '.join(SECTIONS)})")
    out = {}
    for name, cls in SECTIONS.items():
        values = dict(found.get(name, {}))
        if isinstance(values.get("thresholds"), list):
            values["thresholds"] = tuple(values["thresholds"])
        out[KEYWORDS[name]] = cls(**values)
    return out


def write_settings(path: str | os.PathLike, filter_config: FilterConfig, triangle_config: TriangleConfig,
                   fit_config: FitConfig) -> None:
    """Write ``pipeline.json`` whole: every field of every section :func:`read_settings` reads."""
    settings = {"filtering": asdict(filter_config), "faces": asdict(triangle_config), "fit": asdict(fit_config)}
    Path(path).write_text(json.dumps(settings, indent=2) + "\n")
