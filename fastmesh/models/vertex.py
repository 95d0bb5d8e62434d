"""Stage I: the vertex decoder.

A decoder-only transformer over FastMesh vertex tokens (``tokenizer.vertex``),
conditioned by a prefix of point-encoder latents:

    [latent_1 .. latent_M] BOS B O O O B O O ... EOS

Each token's input embedding adds what the grammar already implies: a block
token embeds its block's three axis coordinates, an offset token the full 7-bit
cell of its vertex (current block + offset), so the network never has to
reconstruct absolute positions from the history.  The grammar also masks the
logits, in training and decoding alike (``grammar_mask``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
import torch.nn.functional as F
from torch import nn

from ..params import DEFAULT_VERTEX_LIMIT
from ..tokenizer import vertex as vt
from ..tokenizer.grid import BLOCK_SIDE, BLOCKS_PER_AXIS, block_coords, offset_coords, quantize
from .encoder import EncoderConfig, PointEncoder
from .evidence import Evidence, PointEvidence
from .layers import Block, CoordEmbedding, RMSNorm, init_weights, rotary


@dataclass
class VertexConfig:
    dim: int = 256
    depth: int = 6
    heads: int = 8
    encoder: EncoderConfig = field(default_factory=EncoderConfig)
    max_vertices: int = DEFAULT_VERTEX_LIMIT  # the data variant it was trained on (1000 or 4000)
    evidence: bool = False  # add the learned point-evidence logit bias (models.evidence)
    evidence_normals: bool = False  # ... and its normal-spread ("corner") table
    evidence_cells: bool = False  # ... and the cell log-odds of models.cells
    evidence_blocks_ahead: bool = True  # EOS and block skips also read the occupied blocks ahead (models.evidence)
    count_condition: bool = False  # one more prefix token: the face count asked for (or "the model's choice")
    evidence_counts: bool = False  # EOS and staying in a block also read the counts emitted against the cells

    @property
    def head_dim(self) -> int:
        return self.dim // self.heads

    @classmethod
    def from_name(cls, name: str) -> VertexConfig:
        """The named decoder of :data:`VERTEX_CONFIGS` (``"shipped"``: the one in ``fastmesh/weights/vertex``)."""
        if name not in VERTEX_CONFIGS:
            raise ValueError(f"unknown vertex decoder {name!r}; named ones: {', '.join(VERTEX_CONFIGS)}")
        d = VERTEX_CONFIGS[name]
        return cls(**{**d, "encoder": EncoderConfig(**d["encoder"])})


# Named decoders, as gpt-fast's ``transformer_configs``.  The dataclass's own defaults are the plain decoder (no
# evidence biases, no face-count condition), which the unit tests build small; "shipped" is the decoder of
# fastmesh/weights/vertex, flags and sizes (tests/test_pipeline.py checks it against that config.json).
VERTEX_CONFIGS: dict[str, dict] = {
    "shipped": {"dim": 192, "depth": 6, "heads": 6, "max_vertices": 1000,
                "encoder": {"n_points": 2048, "n_latents": 64, "dim": 192, "depth": 2, "heads": 4, "n_freqs": 8,
                            "anchors": 128},
                "evidence": True, "evidence_normals": True, "evidence_cells": True, "evidence_blocks_ahead": False,
                "count_condition": True, "evidence_counts": True},
}


def grammar_state(tokens: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Current block id and last offset id after each position of (B, T) token ids (-1 where none)."""
    is_block = (tokens >= vt.BLOCK0) & (tokens < vt.OFFSET0)
    is_off = tokens >= vt.OFFSET0
    # Blocks strictly increase along a sequence, so the current block is a running max.
    block = torch.where(is_block, tokens - vt.BLOCK0, torch.full_like(tokens, -1)).cummax(dim=1).values
    offset = torch.where(is_off, tokens - vt.OFFSET0, torch.full_like(tokens, -1))
    return block, offset


def sequence_counts(tokens: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Vertices emitted up to each position of (B, T) token ids, and of them those in the current block."""
    is_off = (tokens >= vt.OFFSET0).long()
    n_vert = is_off.cumsum(1)
    is_block = (tokens >= vt.BLOCK0) & (tokens < vt.OFFSET0)
    # n_vert never decreases, so its value at the last block token is a running max.
    at_block = torch.where(is_block, n_vert, torch.zeros_like(n_vert)).cummax(dim=1).values
    return n_vert, n_vert - at_block


def grammar_mask(prev: torch.Tensor, block: torch.Tensor, offset: torch.Tensor,
                 eos_only: torch.Tensor | None = None) -> torch.Tensor:
    """Boolean (…, VOCAB) mask of the tokens allowed after ``prev`` (see ``vertex.allowed_ranges``).

    ``eos_only`` (…) forces EOS where the vertex budget is spent (``prev`` must be an offset).
    """
    ids = torch.arange(vt.VOCAB_SIZE, device=prev.device)
    p, b, o = prev[..., None], block[..., None], offset[..., None]
    after_bos = (p == vt.BOS) & (ids >= vt.BLOCK0) & (ids < vt.OFFSET0)
    after_block = (p >= vt.BLOCK0) & (p < vt.OFFSET0) & (ids >= vt.OFFSET0)
    is_off = p >= vt.OFFSET0
    after_off = is_off & ((ids == vt.EOS) | ((ids > vt.BLOCK0 + b) & (ids < vt.OFFSET0)) | (ids > vt.OFFSET0 + o))
    mask = after_bos | after_block | after_off
    if eos_only is not None:
        mask = torch.where(eos_only[..., None] & is_off, ids == vt.EOS, mask)
    dead = (p == vt.EOS) | (p == vt.PAD)
    return mask | (dead & (ids == vt.PAD))


def grammar_mask_rows(prev: list[int], block: list[int], offset: list[int], eos_only: list[bool],
                      device: torch.device | str = "cpu") -> torch.Tensor:
    """(B, VOCAB) :func:`grammar_mask` of B decoding rows given as Python lists: a few slice writes per row
    instead of two dozen vocabulary-wide comparisons, for the decode loop (which builds one mask per token)."""
    mask = torch.zeros(len(prev), vt.VOCAB_SIZE, dtype=torch.bool, device=device)
    for i, (p, b, o, e) in enumerate(zip(prev, block, offset, eos_only, strict=True)):
        if p == vt.BOS:
            mask[i, vt.BLOCK0:vt.OFFSET0] = True
        elif vt.BLOCK0 <= p < vt.OFFSET0:
            mask[i, vt.OFFSET0:] = True
        elif p >= vt.OFFSET0:
            mask[i, vt.EOS] = True
            if not e:
                mask[i, vt.BLOCK0 + b + 1:vt.OFFSET0] = True
                mask[i, vt.OFFSET0 + o + 1:] = True
        else:  # after EOS or PAD: PAD only
            mask[i, vt.PAD] = True
    return mask


# Face counts asked for, in buckets of a quarter octave from 16 to 4096 faces; bucket 0 is "no target".
COUNT_MIN, COUNT_MAX, COUNT_STEPS_PER_OCTAVE = 16, 4096, 4
COUNT_BUCKETS = 2 + COUNT_STEPS_PER_OCTAVE * 8
# Faces per vertex of a target: the median of the corpus's meshes (1.69; a closed mesh has about 2).
FACES_PER_VERTEX = 1.7


def count_bucket(target_faces: torch.Tensor) -> torch.Tensor:
    """(B,) face counts asked for (0 or less: none) -> (B,) bucket ids of the count token."""
    t = target_faces.float()
    b = 1 + (COUNT_STEPS_PER_OCTAVE * torch.log2(t.clamp(COUNT_MIN, COUNT_MAX) / COUNT_MIN)).round().long()
    return torch.where(t > 0, b, 0)


def target_vertices(target_faces: torch.Tensor | None) -> torch.Tensor | None:
    """(B,) face counts asked for (0 or less: none) -> (B,) vertex counts the evidence reads (0: none)."""
    if target_faces is None:
        return None
    return torch.where(target_faces > 0, target_faces.float() / FACES_PER_VERTEX, 0.0)


def add_count_bias(logits: torch.Tensor, eos: torch.Tensor, stay: torch.Tensor) -> torch.Tensor:
    """(…, VOCAB) logits plus the count reading of ``Evidence.count_bias``: (…) on EOS, (…) on every offset."""
    bias = torch.zeros_like(logits[..., :vt.OFFSET0])
    bias[..., vt.EOS] = eos
    return logits + torch.cat([bias, stay[..., None].expand(*stay.shape, vt.N_OFFSETS)], dim=-1)


def next_token_loss(logits: torch.Tensor, tokens: torch.Tensor) -> torch.Tensor:
    """Cross entropy of logits (B, T-1, V) against tokens[:, 1:], PAD ignored."""
    target = tokens[:, 1:]
    return F.cross_entropy(logits.reshape(-1, logits.shape[-1]), target.reshape(-1), ignore_index=vt.PAD)


class VertexDecoder(nn.Module):
    def __init__(self, cfg: VertexConfig):
        super().__init__()
        self.cfg = cfg
        self.encoder = PointEncoder(cfg.encoder)
        self.cond_proj = nn.Linear(cfg.encoder.dim, cfg.dim, bias=False)
        self.tok_emb = nn.Embedding(vt.VOCAB_SIZE, cfg.dim)
        self.cell_emb = CoordEmbedding(cfg.dim)  # full cell of an offset token
        self.block_emb = CoordEmbedding(cfg.dim, levels=BLOCKS_PER_AXIS)  # block coordinates of a block token
        self.layers = nn.ModuleList([Block(cfg.dim, cfg.heads) for _ in range(cfg.depth)])
        self.norm = RMSNorm(cfg.dim)
        self.head = nn.Linear(cfg.dim, vt.VOCAB_SIZE, bias=False)
        self.count_emb = nn.Embedding(COUNT_BUCKETS, cfg.dim) if cfg.count_condition else None
        init_weights(self)
        # after init_weights: its tables start at zero (no bias until training finds the evidence useful)
        self.evidence = PointEvidence(normals=cfg.evidence_normals, logodds=cfg.evidence_cells,
                                      blocks_ahead=cfg.evidence_blocks_ahead,
                                      counts=cfg.evidence_counts) if cfg.evidence else None

    # ------------------------------------------------------------------ pieces

    def condition(self, points: torch.Tensor, normals: torch.Tensor,
                  target_faces: torch.Tensor | None = None) -> torch.Tensor:
        """(B, P, 3) points + normals -> (B, M, dim) prefix.

        Anchored encoders (``EncoderConfig.anchors``) also add the cell embedding of each
        anchor's 7-bit cell, the same table offset tokens use for their vertex: a vertex
        token and an input region at the same place start out similar.  With
        ``count_condition`` the prefix ends with a token for ``target_faces`` (B,) (0 or None:
        the model chooses the count itself; trained with both).
        """
        latents, anchor_pts = self.encoder(points, normals, return_anchors=True)
        prefix = self.cond_proj(latents)
        if anchor_pts is not None:
            prefix = prefix + self.cell_emb(quantize(anchor_pts.float()))
        if self.count_emb is not None:
            if target_faces is None:
                target_faces = torch.zeros(prefix.shape[0], dtype=torch.long, device=prefix.device)
            prefix = torch.cat([prefix, self.count_emb(count_bucket(target_faces))[:, None]], dim=1)
        return prefix

    def point_evidence(self, points: torch.Tensor, normals: torch.Tensor | None = None,
                       logodds: torch.Tensor | None = None, target_faces: torch.Tensor | None = None
                       ) -> Evidence | None:
        """(B, P, 3) points (and normals, (B, 128^3) cell log-odds from ``models.cells`` and (B,) face counts
        asked for) -> the :class:`Evidence` whose logit bias ``forward``/``generate`` add (None if off)."""
        if self.evidence is None:
            return None
        return self.evidence(points, normals, logodds, target_vertices(target_faces))

    def embed(self, tokens: torch.Tensor, block: torch.Tensor) -> torch.Tensor:
        """(B, T) tokens and their current block (from ``grammar_state``) -> (B, T, dim)."""
        x = self.tok_emb(tokens)
        is_block = ((tokens >= vt.BLOCK0) & (tokens < vt.OFFSET0))[..., None]
        is_off = (tokens >= vt.OFFSET0)[..., None]
        # Both held to their id ranges, so the tables are read in range whatever state a caller passes.
        bxyz = block_coords(block.clamp(0, vt.N_BLOCKS - 1))
        cell = bxyz * BLOCK_SIDE + offset_coords((tokens - vt.OFFSET0).clamp(0, vt.N_OFFSETS - 1))
        return x + is_block * self.block_emb(bxyz) + is_off * self.cell_emb(cell)

    def _run(self, x: torch.Tensor, start: int, kv_cache=None, is_causal: bool = True) -> torch.Tensor:
        pos = torch.arange(start, start + x.shape[1], device=x.device)
        rope = rotary(pos, self.cfg.head_dim)
        for i, layer in enumerate(self.layers):
            x = layer(x, rope=rope, is_causal=is_causal, kv_cache=kv_cache, layer=i, cache_pos=start)
        return self.head(self.norm(x))

    # ------------------------------------------------------------------ training / reference

    def forward(self, tokens: torch.Tensor, prefix: torch.Tensor | None = None,
                points: torch.Tensor | None = None, normals: torch.Tensor | None = None,
                evidence: Evidence | None = None, logodds: torch.Tensor | None = None,
                target_faces: torch.Tensor | None = None) -> torch.Tensor:
        """Uncached pass: tokens (B, T) -> logits (B, T, VOCAB) for the *next* token.

        The condition is ``prefix`` (B, M, dim) and ``evidence``, or both computed from
        ``points``/``normals`` (B, P, 3), ``logodds`` (B, 128^3) and ``target_faces`` (B,) (the training path,
        so DDP sees one forward).
        Grammar masking is applied here too, so training and decoding see the same distribution.
        """
        if prefix is None:
            prefix = self.condition(points, normals, target_faces)
            evidence = self.point_evidence(points, normals, logodds, target_faces)
        block, offset = grammar_state(tokens)
        x = torch.cat([prefix.to(self.tok_emb.weight.dtype), self.embed(tokens, block)], dim=1)
        logits = self._run(x, 0)[:, prefix.shape[1]:].float()
        if evidence is not None:
            logits = logits + evidence.logit_bias(block)
            if self.cfg.evidence_counts:
                logits = add_count_bias(logits, *evidence.count_bias(block, offset, *sequence_counts(tokens)))
        return logits.masked_fill(~grammar_mask(tokens, block, offset), float("-inf"))

    def loss(self, tokens: torch.Tensor, **cond) -> torch.Tensor:
        """Next-token cross entropy over BOS..EOS of padded (B, T) sequences."""
        return next_token_loss(self(tokens[:, :-1], **cond), tokens)

    # ------------------------------------------------------------------ incremental

    def prefill(self, prefix: torch.Tensor, tokens: torch.Tensor, kv_cache) -> torch.Tensor:
        """Run prefix + first tokens at position 0 into the cache; logits (B, VOCAB) of the last."""
        block, _ = grammar_state(tokens)
        x = torch.cat([prefix, self.embed(tokens, block)], dim=1)
        return self._run(x, 0, kv_cache=kv_cache)[:, -1].float()

    def decode_step(self, tokens: torch.Tensor, block: torch.Tensor, pos: int, kv_cache) -> torch.Tensor:
        """One token per sequence (B, 1) at cache position ``pos`` -> logits (B, VOCAB)."""
        x = self.embed(tokens, block)
        return self._run(x, pos, kv_cache=kv_cache, is_causal=False)[:, -1].float()
