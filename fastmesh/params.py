"""User-facing generation parameters (no torch import: the CLI and service read them cheaply)."""

from __future__ import annotations

from dataclasses import dataclass

MAX_CANDIDATES = 16  # each candidate costs a full generation
TARGET_FACES = (4, 8000)  # faces a user may ask for; the decoder's vertex limit still caps the result
# Smallest non-zero temperature: logits / temperature must stay finite in float32 (0 means greedy decoding).
MIN_TEMPERATURE = 1e-3
MAX_TEMPERATURE = 5.0


@dataclass
class SamplingConfig:
    temperature: float = 0.3
    top_k: int = 50
    top_p: float = 0.95
    max_vertices: int = 1000
    seed: int = 0

    def validate(self) -> None:
        if not (self.temperature == 0 or MIN_TEMPERATURE <= self.temperature <= MAX_TEMPERATURE):
            raise ValueError(f"temperature must be 0 (greedy) or in [{MIN_TEMPERATURE:g}, {MAX_TEMPERATURE:g}]")
        if self.top_k < 0:
            raise ValueError("top_k must be >= 0 (0 disables it)")
        if not 0 < self.top_p <= 1:
            raise ValueError("top_p must be in (0, 1]")
        if self.max_vertices < 3:
            raise ValueError("max_vertices must be at least 3")


@dataclass
class GenerateParams:
    """User-facing generation settings (the service's form fields have the same names)."""

    seed: int = 0
    temperature: float = 0.3
    top_k: int = 50
    top_p: float = 0.95
    max_vertices: int | None = None  # None: the vertex model's own limit
    enhancer: bool = True
    filtering: bool = True
    candidates: int = 2  # meshes made (seeds seed, seed+1, ...); the one nearest the input is returned
    target_faces: int | None = None  # faces asked for; None: the model chooses the count itself

    def validate(self, limit: int = 4000) -> None:
        """Raise ValueError naming the first bad field."""
        if not isinstance(self.seed, int) or not 0 <= self.seed < 2**63 - MAX_CANDIDATES:
            raise ValueError(f"seed must be an integer in [0, 2^63 - {MAX_CANDIDATES})")
        if not isinstance(self.candidates, int) or not 1 <= self.candidates <= MAX_CANDIDATES:
            raise ValueError(f"candidates must be an integer in [1, {MAX_CANDIDATES}]")
        lo, hi = TARGET_FACES
        if self.target_faces is not None and (not isinstance(self.target_faces, int)
                                              or not lo <= self.target_faces <= hi):
            raise ValueError(f"target_faces must be an integer in [{lo}, {hi}]")
        if self.max_vertices is not None and not 3 <= self.max_vertices <= limit:
            raise ValueError(f"max_vertices must be in [3, {limit}]")
        self.sampling(limit).validate()

    def sampling(self, limit: int):
        """The decoder's ``SamplingConfig`` with ``max_vertices`` resolved against ``limit``."""
        max_v = limit if self.max_vertices is None else min(int(self.max_vertices), limit)
        return SamplingConfig(temperature=float(self.temperature), top_k=int(self.top_k), top_p=float(self.top_p),
                              max_vertices=max_v, seed=int(self.seed))
