"""One task per network: how to build it, batch the data, and score a batch.

A task is a small object with ``kind``, ``build_model(overrides)``, ``costs(ds)``
(per-mesh cost for length bucketing), ``make_batch(ds, indices, rng, cfg, train)``
and ``loss(model, batch) -> (loss, n_items)``.  The generic loop in ``loop.py``
does the rest.
"""

from __future__ import annotations

import numpy as np
import torch

from ..models.checkpoint import config_from_dict, registry
from ..tokenizer import vertex as vt
from .augment import prepare_sample


def _points_tensors(samples) -> dict[str, torch.Tensor]:
    return {"points": torch.from_numpy(np.stack([s[3] for s in samples])),
            "normals": torch.from_numpy(np.stack([s[4] for s in samples]))}


class VertexTask:
    kind = "vertex"

    def build_model(self, overrides: dict):
        cls, cfg_cls = registry(self.kind)
        return cls(config_from_dict(cfg_cls, overrides))

    def costs(self, ds) -> np.ndarray:
        """Token count of each mesh (unaugmented; augmentation changes it by a few %)."""
        return np.array([vt.num_tokens(ds.a["q"][a:b].astype(np.int64))
                         for a, b in zip(ds.a["v_off"][:-1], ds.a["v_off"][1:], strict=True)])

    def make_batch(self, ds, indices, rng: np.random.Generator, cfg, train: bool) -> dict[str, torch.Tensor]:
        n_points = _n_points(cfg)
        samples = []
        for i in indices:
            rec = ds[int(i)]
            samples.append(prepare_sample(rec.continuous, rec.faces, n_points, cfg.augment if train else None, rng))
        seqs = [vt.encode(s[0]) for s in samples]
        tokens = np.full((len(seqs), max(map(len, seqs))), vt.PAD, dtype=np.int64)
        for r, s in enumerate(seqs):
            tokens[r, : len(s)] = s
        return {"tokens": torch.from_numpy(tokens), **_points_tensors(samples)}

    def loss(self, model, batch):
        loss = model.loss(batch["tokens"], points=batch["points"], normals=batch["normals"])
        return loss, int((batch["tokens"][:, 1:] != vt.PAD).sum())


def _n_points(cfg) -> int:
    enc = cfg.model.get("encoder", {})
    return int(enc.get("n_points", 2048))


TASKS = {"vertex": VertexTask}
