"""One task per network: how to build it, batch the data, and score a batch.

A task is a small object with ``kind``, ``build_model(overrides)``, ``costs(ds)``
(per-mesh cost for length bucketing), ``make_batch(ds, indices, rng, cfg, train)``
and ``loss(model, batch) -> (loss, n_items)``.  The generic loop in ``loop.py``
does the rest.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch
import torch.nn.functional as F

from ..evaluation.metrics import edge_metrics
from ..faces.filtering import adjacency_bandwidth, band_mask, edges_from_logits, neighbour_radius, rcm_order
from ..faces.meshops import edges_from_faces
from ..models.checkpoint import config_from_dict, registry
from ..tokenizer import dequantize
from ..tokenizer import vertex as vt
from ..tokenizer.grid import CELL, LEVELS, N_CELLS, flat_index, unflat_index
from .augment import apply_symmetry, grid_symmetry, perturb_vertex_set, prepare_sample, symmetric_cells


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
        return np.array([vt.num_tokens(ds.arrays["q"][a:b].astype(np.int64))
                         for a, b in zip(ds.arrays["v_off"][:-1], ds.arrays["v_off"][1:], strict=True)])

    def make_batch(self, ds, indices, rng: np.random.Generator, cfg, train: bool) -> dict[str, torch.Tensor]:
        """Tokens, condition points and (for a decoder that reads them) the stored cell log-odds.

        The log-odds in a cell cache (``fastmesh data cells``) are those of the unaugmented mesh, so
        a decoder that reads them trains on the mesh under one of the cube's 48 symmetries (which
        carry the stored log-odds along) and jittered points, not under free rotations and scales.
        """
        n_points = _n_points(cfg)
        reads_logodds = bool(cfg.model.get("evidence_cells"))
        augment = cfg.augment if train else None
        if reads_logodds and train:
            augment = dataclasses.replace(cfg.augment, rotate=False, scale_min=1.0)
        samples, syms = [], []
        for i in indices:
            rec = ds[int(i)]
            v = rec.continuous
            sym = grid_symmetry(rng) if reads_logodds and train else None
            if sym is not None:
                v = apply_symmetry(v, sym)
            syms.append(sym)
            samples.append(prepare_sample(v, rec.faces, n_points, augment, rng))
        seqs = [vt.encode(s[0]) for s in samples]
        tokens = np.full((len(seqs), max(map(len, seqs))), vt.PAD, dtype=np.int64)
        for r, s in enumerate(seqs):
            tokens[r, : len(s)] = s
        batch = {"tokens": torch.from_numpy(tokens), **_points_tensors(samples)}
        if reads_logodds:
            batch.update(sparse_cells(ds, indices, syms))
        if cfg.model.get("count_condition"):
            # The true face count as the condition, dropped at random so "the model's choice" is trained
            # (and validated) too.
            faces = np.array([len(s[1]) for s in samples])
            drop = rng.random(len(faces)) < COUNT_DROP
            batch["target_faces"] = torch.from_numpy(np.where(drop, 0, faces))
        return batch

    def loss(self, model, batch):
        logodds = dense_cells(batch["cell_flat"], batch["cell_logit"]) if "cell_flat" in batch else None
        loss = model.loss(batch["tokens"], points=batch["points"], normals=batch["normals"], logodds=logodds,
                          target_faces=batch.get("target_faces"))
        return loss, int((batch["tokens"][:, 1:] != vt.PAD).sum())

    @torch.no_grad()
    def evaluate(self, model, ds, val_idx, cfg, device) -> dict:
        """How much the condition helps: loss with each mesh's points minus loss with another mesh's.

        ``cond_gain`` (nats per token) near 0 means the decoder ignores its input and
        generates the same artist-like sequences for every shape.
        """
        idx = np.sort(val_idx)[:: max(1, len(val_idx) // 16)][:16]
        if len(idx) < 2:
            return {}
        b = {k: v.to(device) for k, v in self.make_batch(ds, idx, np.random.default_rng(0), cfg, train=False).items()}
        own = float(self.loss(model, b)[0])
        other = float(self.loss(model, {k: v.roll(1, 0) if k != "tokens" else v for k, v in b.items()})[0])
        return {"cond_gain": round(other - own, 5)}


COUNT_DROP = 0.5  # share of training sequences whose face count is not given


def sparse_cells(ds, indices, syms=None) -> dict[str, torch.Tensor]:
    """The stored cell log-odds of some meshes as padded (B, K) flat cell indices and log-odds.

    A batch carries them sparse (a dense grid is 8 MB per mesh) and ``dense_cells`` spreads them
    where the model runs; padding points at an extra cell past the grid.  ``syms`` (one per mesh,
    or None) moves each mesh's cells by a symmetry of ``augment.grid_symmetry``.
    """
    from ..models.cells import FLOOR

    stored = [ds.cells(int(i)) for i in indices]
    k = max(1, max(len(f) for f, _ in stored))
    flat = torch.full((len(stored), k), N_CELLS, dtype=torch.long)
    logit = torch.full((len(stored), k), FLOOR)
    for r, (f, lo) in enumerate(stored):
        f = torch.from_numpy(f.astype(np.int64))
        if syms is not None and syms[r] is not None:
            f = flat_index(torch.from_numpy(symmetric_cells(unflat_index(f).numpy(), syms[r], LEVELS)))
        flat[r, : len(f)] = f
        logit[r, : len(f)] = torch.from_numpy(lo.astype(np.float32))
    return {"cell_flat": flat, "cell_logit": logit}


def dense_cells(flat: torch.Tensor, logit: torch.Tensor) -> torch.Tensor:
    """(B, K) from ``sparse_cells`` -> (B, 128^3) float32 log-odds grids, ``FLOOR`` off the candidates."""
    from ..models.cells import FLOOR

    grid = torch.full((len(flat), N_CELLS + 1), FLOOR, device=flat.device)
    return grid.scatter_(1, flat, logit.float().clamp(min=FLOOR))[:, :-1]


def _n_points(cfg) -> int:
    enc = cfg.model.get("encoder", {})
    return int(enc.get("n_points", 2048))


def _unwrap(model):
    return model.module if hasattr(model, "module") else model


def _pad_cells(qs: list[np.ndarray]) -> tuple[torch.Tensor, torch.Tensor]:
    """List of (V_i, 3) cells -> padded (B, N, 3) long and valid (B, N) bool."""
    n = max(len(q) for q in qs)
    out = np.zeros((len(qs), n, 3), dtype=np.int64)
    valid = np.zeros((len(qs), n), dtype=bool)
    for r, q in enumerate(qs):
        out[r, : len(q)] = q
        valid[r, : len(q)] = True
    return torch.from_numpy(out), torch.from_numpy(valid)


class _SetTask:
    """Shared by the enhancer and face tasks: one augmented sample per mesh, padded vertex sets."""

    kind = ""

    def build_model(self, overrides: dict):
        cls, cfg_cls = registry(self.kind)
        return cls(config_from_dict(cfg_cls, overrides))

    def costs(self, ds) -> np.ndarray:
        return ds.num_vertices().astype(np.int64)

    def _samples(self, ds, indices, rng, cfg, train: bool):
        n_points = _n_points(cfg)
        recs = [ds[int(i)] for i in indices]
        return [prepare_sample(r.continuous, r.faces, n_points, cfg.augment if train else None, rng) for r in recs]


class EnhancerTask(_SetTask):
    """Residual of each (re-quantised) vertex inside its cell, in cells, L1 loss."""

    kind = "enhancer"

    def make_batch(self, ds, indices, rng: np.random.Generator, cfg, train: bool) -> dict[str, torch.Tensor]:
        samples = self._samples(ds, indices, rng, cfg, train)
        q, valid = _pad_cells([s[0] for s in samples])
        target = np.zeros(q.shape, dtype=np.float32)
        for r, s in enumerate(samples):
            target[r, : len(s[0])] = np.clip((s[2] - dequantize(s[0])) / CELL, -0.5, 0.5)
        return {"q": q, "valid": valid, "target": torch.from_numpy(target), **_points_tensors(samples)}

    def loss(self, model, batch):
        pred = model(batch["q"], batch["points"], batch["normals"], batch["valid"])
        return _unwrap(model).l1(pred, batch["target"], batch["valid"]), int(batch["valid"].sum())

    def evaluate(self, model, ds, val_idx, cfg, device) -> dict:
        """L1 of predicting zero residual (the cell centre) on the validation batches, for comparison."""
        idx = np.sort(val_idx)[: cfg.val_batches * 4]
        b = self.make_batch(ds, idx, np.random.default_rng(0), cfg, train=False)
        w = b["valid"][..., None].float()
        return {"zero_l1": round(float((b["target"].abs() * w).sum() / (3 * w.sum())), 5)}


# Mask kinds of the face task and their probabilities (METHOD.md, the authors' experimental code).
FACE_MASKS = {"candidate": 0.3, "bandwidth": 0.2, "full": 0.1, "negative": 0.4}
NEGATIVE_RATIO = 8.0  # negatives sampled per positive pair in "negative" samples
RADIUS_SLACK = (1.0, 1.5, 4)  # mask radii scaled by U(a, b) plus randint(0, c): inferred masks are looser
FACE_EVAL_MESHES = 24  # validation meshes (<= FACE_EVAL_MAX_VERTICES) scored for edge P/R/F1
FACE_EVAL_MAX_VERTICES = 500


def face_training_mask(edges: np.ndarray, n: int, kind: str, rng: np.random.Generator):
    """Vertex order, attention mask and scored pairs of one training sample.

    Parameters
    ----------
    edges : (E, 2) true edges (i < j) in canonical order.
    kind : "full" (all pairs), "negative" (full attention; loss on the positives plus
        ``NEGATIVE_RATIO`` random negatives per positive), "bandwidth" or "candidate" (the
        masks of prediction filtering built from the true edges in reverse Cuthill-McKee
        order, radii loosened by ``RADIUS_SLACK`` as predicted edges would).

    Returns
    -------
    order : (n,) permutation (position k holds vertex order[k]); attn : (n, n) bool or None;
    score : (n, n) bool, the pairs (upper triangle) that enter the loss.
    """
    order = np.arange(n)
    upper = np.triu(np.ones((n, n), dtype=bool), 1)
    if kind == "full":
        return order, None, upper
    if kind == "negative":
        n_pairs = max(n * (n - 1) // 2, 1)
        rate = min(1.0, NEGATIVE_RATIO * len(edges) / n_pairs)
        score = rng.random((n, n)) < rate
        score[edges[:, 0], edges[:, 1]] = True
        return order, None, score & upper
    order = rcm_order(edges, n)
    pos = np.empty(n, dtype=np.int64)
    pos[order] = np.arange(n)
    e = np.sort(pos[edges], axis=1) if len(edges) else edges
    lo, hi, extra = RADIUS_SLACK
    if kind == "bandwidth":
        b = adjacency_bandwidth(e)
        mask = band_mask(n, max(2, int(np.ceil(b * rng.uniform(lo, hi))) + int(rng.integers(0, extra + 1))))
    elif kind == "candidate":
        r = neighbour_radius(e, n, 2)
        r = np.ceil(r * rng.uniform(lo, hi, n)).astype(np.int64) + rng.integers(0, extra + 1, n)
        mask = band_mask(n, r)
    else:
        raise ValueError(f"unknown mask kind {kind!r}")
    return order, mask, mask & mask.T & upper


class FaceTask(_SetTask):
    """Adjacency of the (re-quantised) mesh, asymmetric loss over pairs, random filtering masks."""

    kind = "face"

    def costs(self, ds) -> np.ndarray:
        """Pairs per mesh: the edge head and the loss are quadratic in the vertex count."""
        return ds.num_vertices().astype(np.int64) ** 2

    def make_batch(self, ds, indices, rng: np.random.Generator, cfg, train: bool) -> dict[str, torch.Tensor]:
        samples = self._samples(ds, indices, rng, cfg, train)
        kinds, probs = list(FACE_MASKS), np.array(list(FACE_MASKS.values()))
        qs, parts = [], []
        for s in samples:
            q, f = s[0], s[1]
            if train and cfg.augment.perturb > 0 and rng.random() < cfg.augment.perturb:
                q, f = perturb_vertex_set(q, f, cfg.augment, rng)
            n = len(q)
            edges = edges_from_faces(f)
            kind = kinds[rng.choice(len(kinds), p=probs / probs.sum())] if train else "full"
            order, attn, score = face_training_mask(edges, n, kind, rng)
            pos = np.empty(n, dtype=np.int64)
            pos[order] = np.arange(n)
            target = np.zeros((n, n), dtype=bool)
            if len(edges):
                e = np.sort(pos[edges], axis=1)
                target[e[:, 0], e[:, 1]] = True
            qs.append(q[order])
            parts.append((attn, target, score))
        qt, valid = _pad_cells(qs)
        b, n = valid.shape
        mask = np.ones((b, n, n), dtype=bool)
        target = np.zeros((b, n, n), dtype=bool)
        score = np.zeros((b, n, n), dtype=bool)
        for r, (a, t, sc) in enumerate(parts):
            k = len(t)
            if a is not None:
                mask[r, :k, :k] = a
            target[r, :k, :k], score[r, :k, :k] = t, sc
        return {"q": qt, "valid": valid, "mask": torch.from_numpy(mask), "target": torch.from_numpy(target),
                "score": torch.from_numpy(score), **_points_tensors(samples)}

    def loss(self, model, batch):
        from ..models.face import asymmetric_loss

        logits = model(batch["q"], batch["points"], batch["normals"], valid=batch["valid"], mask=batch["mask"])
        n_pos = int((batch["target"] & batch["score"]).sum())
        return asymmetric_loss(logits, batch["target"], batch["score"]) / max(n_pos, 1), n_pos

    def evaluate(self, model, ds, val_idx, cfg, device) -> dict:
        """Edge precision / recall / F1 (means over meshes) at probability 0.5, one unmasked pass."""
        net = _unwrap(model)
        nv = ds.num_vertices()
        idx = np.sort(val_idx)
        idx = idx[nv[idx] <= FACE_EVAL_MAX_VERTICES][:FACE_EVAL_MESHES]
        if len(idx) == 0:
            return {}
        rng = np.random.default_rng(0)
        scores = []
        for i in idx:
            q, f, _, pts, nrm = self._samples(ds, [i], rng, cfg, train=False)[0]
            logits = net(torch.from_numpy(q).to(device)[None], torch.from_numpy(pts).to(device)[None],
                         torch.from_numpy(nrm).to(device)[None])[0].float().cpu().numpy()
            scores.append(edge_metrics(edges_from_logits(logits, 0.5), edges_from_faces(f)))
        return {k: round(float(np.mean([s[k] for s in scores])), 4) for k in ("precision", "recall", "f1")}


class CellTask:
    """The cell evidence network: every candidate cell of each mesh, labelled "an artist vertex's cell".

    A mesh has ~10^5 candidate cells and a few hundred vertices: all positives are kept and a
    ``CELL_NEGATIVES`` share of the negatives, weighted back up, so the log-odds stay calibrated.
    """

    kind = "cells"

    def build_model(self, overrides: dict):
        cls, cfg_cls = registry(self.kind)
        return cls(config_from_dict(cfg_cls, overrides))

    def costs(self, ds) -> np.ndarray:
        return np.ones(len(ds), dtype=np.int64)  # batch_cost = meshes per batch

    def make_batch(self, ds, indices, rng: np.random.Generator, cfg, train: bool) -> dict[str, torch.Tensor]:
        from ..models.cells import CellNetConfig, candidate_cells, cell_features

        n_points = int(cfg.model.get("n_points", CellNetConfig.n_points))
        plane_fit = bool(cfg.model.get("plane_fit", CellNetConfig.plane_fit))
        feats, labels, weights = [], [], []
        for i in indices:
            rec = ds[int(i)]
            q, _, _, pts, nrm = prepare_sample(rec.continuous, rec.faces, n_points, cfg.augment if train else None, rng)
            cells, nearest = candidate_cells(torch.from_numpy(pts))
            label = np.isin(flat_index(cells).numpy(), flat_index(torch.from_numpy(q)).numpy())
            keep = label | (rng.random(len(label)) < CELL_NEGATIVES)
            feats.append(cell_features(torch.from_numpy(pts), torch.from_numpy(nrm), cells[keep], nearest[keep],
                                       plane_fit))
            labels.append(torch.from_numpy(label[keep]))
            weights.append(torch.from_numpy(np.where(label[keep], 1.0, 1.0 / CELL_NEGATIVES)).float())
        return {"features": torch.cat(feats), "label": torch.cat(labels).float(), "weight": torch.cat(weights)}

    def loss(self, model, batch):
        logits = model(batch["features"]).float()
        bce = F.binary_cross_entropy_with_logits(logits, batch["label"], reduction="none")
        return (bce * batch["weight"]).sum() / batch["weight"].sum(), int(batch["label"].sum())

    def evaluate(self, model, ds, val_idx, cfg, device) -> dict:
        """Precision and recall within one cell of the top cells (one-cell suppression) at the true count."""
        from ..models.cells import select_cells

        net = _unwrap(model)
        idx = np.sort(val_idx)[:: max(1, len(val_idx) // CELL_EVAL_MESHES)][:CELL_EVAL_MESHES]
        rng = np.random.default_rng(0)
        p1, r1 = [], []
        for i in idx:
            rec = ds[int(i)]
            q, _, _, pts, nrm = prepare_sample(rec.continuous, rec.faces, net.cfg.n_points, None, rng)
            cells, logits = net.score(pts, nrm)
            got = select_cells(cells, logits, count=len(q))
            p, r = cell_precision_recall(got, q)
            p1.append(p)
            r1.append(r)
        return {"precision_1": round(float(np.mean(p1)), 4), "recall_1": round(float(np.mean(r1)), 4)}


def cell_precision_recall(cells: np.ndarray, q: np.ndarray, within: float = 1.0) -> tuple[float, float]:
    """Share of ``cells`` within ``within`` cells (between centres) of a vertex cell of ``q``, and the reverse."""
    from scipy.spatial import cKDTree

    if len(cells) == 0 or len(q) == 0:
        return 0.0, 0.0
    d_gen, _ = cKDTree(q).query(cells)
    d_ref, _ = cKDTree(cells).query(q)
    return float((d_gen <= within).mean()), float((d_ref <= within).mean())


CELL_NEGATIVES = 0.05
CELL_EVAL_MESHES = 24

TASKS = {"vertex": VertexTask, "enhancer": EnhancerTask, "face": FaceTask, "cells": CellTask}
