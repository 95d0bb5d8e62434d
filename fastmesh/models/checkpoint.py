"""Saving and loading networks as ``model.safetensors`` + ``config.json``.

``config.json`` holds ``{"kind": "vertex" | "enhancer" | "face" | "cells", "config": {...}}``
where ``config`` is the network's config dataclass as a dict, so a directory is
self-describing and safe to load (safetensors never unpickles).
"""

from __future__ import annotations

import dataclasses
import json
import os
import typing
from pathlib import Path

import torch
from safetensors.torch import load_file, save_file
from torch import nn


def registry(kind: str) -> tuple[type, type]:
    """kind -> (module class, config class); imported lazily so each network stands alone."""
    if kind == "vertex":
        from .vertex import VertexConfig, VertexDecoder

        return VertexDecoder, VertexConfig
    if kind == "enhancer":
        from .enhancer import Enhancer, EnhancerConfig

        return Enhancer, EnhancerConfig
    if kind == "face":
        from .face import FaceModel, FaceModelConfig

        return FaceModel, FaceModelConfig
    if kind == "cells":  # the cell network: the kind its saved config.json files carry
        from .cells import CellNet, CellNetConfig

        return CellNet, CellNetConfig
    raise ValueError(f"unknown network kind {kind!r}")


def config_from_dict(cls, d: dict):
    """Build a (possibly nested) config dataclass from a dict; unknown keys are an error."""
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = set(d) - names
    if unknown:
        raise ValueError(f"unknown {cls.__name__} fields: {sorted(unknown)}")
    kwargs = {}
    for k, v in d.items():
        t = hints[k]
        kwargs[k] = config_from_dict(t, v) if dataclasses.is_dataclass(t) and isinstance(v, dict) else v
    return cls(**kwargs)


def save_model(model: nn.Module, kind: str, directory: str | os.PathLike, extra: dict | None = None,
               dtype: torch.dtype | None = None) -> None:
    """Write ``model.safetensors`` and ``config.json`` atomically (temp file + rename).

    ``dtype`` (e.g. ``torch.float16``) stores floating-point tensors at that precision;
    loading casts them back to the model's own dtype.  The shipped weights use float16
    to halve their size in git.
    """
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    state = {k: v.detach().to("cpu").contiguous() for k, v in _unwrap(model).state_dict().items()}
    if dtype is not None:
        state = {k: v.to(dtype) if v.is_floating_point() else v for k, v in state.items()}
    tmp = d / "model.safetensors.tmp"
    save_file(state, str(tmp))
    os.replace(tmp, d / "model.safetensors")
    meta = {"kind": kind, "config": dataclasses.asdict(_unwrap(model).cfg), **(extra or {})}
    (d / "config.json.tmp").write_text(json.dumps(meta, indent=2))
    os.replace(d / "config.json.tmp", d / "config.json")


def load_model(directory: str | os.PathLike, device: str | torch.device = "cpu") -> tuple[nn.Module, dict]:
    """Load a network saved by :func:`save_model`; returns (model in eval mode, config.json dict)."""
    d = Path(directory)
    cfg_path, w_path = d / "config.json", d / "model.safetensors"
    if not cfg_path.exists() or not w_path.exists():
        raise FileNotFoundError(f"{d} must hold config.json and model.safetensors")
    meta = json.loads(cfg_path.read_text())
    cls, cfg_cls = registry(meta["kind"])
    model = cls(config_from_dict(cfg_cls, meta["config"]))
    model.load_state_dict(load_file(str(w_path), device="cpu"))
    return model.to(device).eval(), meta


def _unwrap(model: nn.Module) -> nn.Module:
    return model.module if hasattr(model, "module") else model
