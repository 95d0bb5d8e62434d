"""TEMPORARY test double of fastmesh.pipeline (same interface)."""
import json
import os
import time
from dataclasses import dataclass, field

import numpy as np

from fastmesh.io import Normalization, export_mesh


class Cancelled(Exception):
    pass


class GenerationError(RuntimeError):
    def __init__(self, code, message):
        super().__init__(message)
        self.code, self.message = code, message


@dataclass
class GenerateParams:
    seed: int = 0
    temperature: float = 0.5
    top_k: int = 10
    top_p: float = 0.95
    max_vertices: int = 64
    enhancer: bool = True
    filtering: bool = True

    def validate(self, limit=4000):
        if not 0 < self.temperature <= 10:
            raise ValueError("temperature: must be in (0, 10]")
        if self.top_k < 1:
            raise ValueError("top_k: must be >= 1")
        if not 0 < self.top_p <= 1:
            raise ValueError("top_p: must be in (0, 1]")
        if self.max_vertices is not None and not 3 <= self.max_vertices <= limit:
            raise ValueError(f"max_vertices must be in [3, {limit}]")


@dataclass
class GenerateResult:
    vertices: np.ndarray
    faces: np.ndarray
    tokens: int
    timings: dict = field(default_factory=dict)

    def export(self, fmt):
        return export_mesh(self.vertices, self.faces, fmt)


class Pipeline:
    max_vertices = 64

    def __init__(self, step=0.002):
        self.step = step

    @classmethod
    def from_pretrained(cls, weights=None, device=None):
        step = 0.002
        if weights and os.path.exists(os.path.join(weights, "fake.json")):
            step = json.load(open(os.path.join(weights, "fake.json")))["step"]
        return cls(step)

    @classmethod
    def random(cls, size="tiny", seed=0):
        return cls()

    def save(self, directory):
        os.makedirs(directory, exist_ok=True)
        json.dump({"step": self.step}, open(os.path.join(directory, "fake.json"), "w"))

    def generate(self, shape, params=GenerateParams(), progress=None, should_cancel=None):
        t = {}
        if params.max_vertices and params.max_vertices > 64:
            raise ValueError("max_vertices must be in [3, 64]")
        t0 = time.perf_counter()
        norm = Normalization.fit(shape.vertices)
        t["encode"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        n = params.max_vertices or 64
        for i in range(n):
            if should_cancel and should_cancel():
                raise Cancelled()
            if progress:
                progress("vertices", 0.03 + 0.77 * i / n)
            time.sleep(self.step)
        t["vertices"] = time.perf_counter() - t0
        v = np.array([[-.5, -.5, -.5], [.5, -.5, -.5], [0, .5, -.5], [0, 0, .5]])
        f = np.array([[0, 2, 1], [0, 1, 3], [1, 2, 3], [2, 0, 3]])
        for k in ("enhancer", "faces", "filtering"):
            t[k] = 0.0
        return GenerateResult(norm.invert(v), f, n, t)
