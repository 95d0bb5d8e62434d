"""Choosing the next vertex token: top-k / top-p filtering, the draw in two steps (the token's kind, then the
token of that kind, ``choose_next``) and the pace that closes a block once a sequence runs ahead of the cells.
:mod:`.generate`'s loop calls them per step; :mod:`.sampling` draws the same two steps from counter-based noise."""

from __future__ import annotations

import torch

from ..params import SamplingConfig
from ..tokenizer import vertex as vt

PACE_SLACK = 4  # vertices a sequence may run ahead of pace x the cells' expected count
KIND_EOS, KIND_BLOCK, KIND_OFFSET = 0, 1, 2  # token kinds of ``choose_next`` (PAD counts as EOS)


def filter_logits(logits: torch.Tensor, top_k: int, top_p: float) -> torch.Tensor:
    """Keep the ``top_k`` largest logits and the smallest set whose probability reaches ``top_p``."""
    if top_k > 0 and top_k < logits.shape[-1]:
        kth = torch.topk(logits, top_k, dim=-1).values[..., -1:]
        logits = logits.masked_fill(logits < kth, float("-inf"))
    if top_p < 1.0:
        sorted_logits, idx = torch.sort(logits, descending=True, dim=-1)
        cum = sorted_logits.softmax(-1).cumsum(-1)
        drop = cum - sorted_logits.softmax(-1) > top_p  # keep the token that crosses top_p
        logits = logits.masked_fill(drop.scatter(-1, idx, drop), float("-inf"))
    return logits


def token_probs(logits: torch.Tensor, cfg: SamplingConfig) -> tuple[torch.Tensor, torch.Tensor]:
    """(B, V) masked logits -> (B, n) probabilities of (B, n) token ids (temperature, top-k, top-p applied).

    With top-k on, only the k best are kept (sorted, from ``topk``): top-p, softmax and the draw then
    run over k values, not the whole vocabulary; the distribution is that of ``filter_logits``.
    """
    if 0 < cfg.top_k < logits.shape[-1]:
        vals, ids = torch.topk(logits / cfg.temperature, cfg.top_k, dim=-1)
        return filter_logits(vals, 0, cfg.top_p).softmax(-1), ids
    ids = torch.arange(logits.shape[-1], device=logits.device).expand_as(logits)
    return filter_logits(logits / cfg.temperature, 0, cfg.top_p).softmax(-1), ids


def sample_next(logits: torch.Tensor, cfg: SamplingConfig,
                gen: torch.Generator | list[torch.Generator] | None) -> torch.Tensor:
    """(B, V) masked logits -> (B,) token ids.

    ``gen``: one generator for the batch, or one per row (row i draws from ``gen[i]`` alone, as it
    would in a batch of one).
    """
    if cfg.temperature == 0:
        return logits.argmax(-1)
    probs, ids = token_probs(logits, cfg)
    if isinstance(gen, list):
        draw = torch.cat([torch.multinomial(probs[i:i + 1], 1, generator=g) for i, g in enumerate(gen)])
    else:
        draw = torch.multinomial(probs, 1, generator=gen)
    return ids.gather(-1, draw).squeeze(-1)


def choose_next(logits: torch.Tensor, cfg: SamplingConfig, gen: list[torch.Generator] | None,
                offset_bias: torch.Tensor | None = None) -> torch.Tensor:
    """(B, V) masked logits -> (B,) token ids, in two steps.

    First the kind of the next token (EOS, a new block, another vertex in this block) from the decoder's
    own probabilities at ``cfg.structure_temperature`` (summed over the tokens of each kind), then the token
    among those of that kind at ``cfg.temperature`` (top-k / top-p within the kind), with ``offset_bias``
    (B, N_OFFSETS) added to the offsets: a weight on the cells among the offsets that leaves the decoder's
    count alone.  Temperature 0 is greedy in both steps.  Row i draws from ``gen[i]`` alone.
    """
    t_kind = cfg.structure_temperature if cfg.temperature > 0 else 0.0
    mass = _kind_mass(logits, t_kind)
    # One NaN logit makes its whole row of probabilities NaN, so a finite mass says the logits hold none (a check
    # of 3 values per row, not of the vocabulary).  NaN tokens are dropped, never drawn: sampling from NaN is an
    # error, and on CUDA a device-side assert that poisons the process.
    if not bool(torch.isfinite(mass).all()):
        logits = _nan_masked(logits)
        mass = _kind_mass(logits, t_kind)
        if not bool(torch.isfinite(mass).all()):  # fail here, on the host, rather than in torch.multinomial
            raise FloatingPointError("the vertex decoder's logits allow no token (none is finite)")
    if t_kind > 0:
        kind = torch.cat([torch.multinomial(mass[i:i + 1], 1, generator=g) for i, g in enumerate(gen)])[:, 0]
    else:
        kind = mass.argmax(-1)
    if offset_bias is not None:  # finite: the evidence reads NaN cell log-odds as no candidate (Evidence)
        logits = torch.cat([logits[:, :vt.OFFSET0], logits[:, vt.OFFSET0:] + offset_bias], dim=-1)
    return sample_next(logits.masked_fill(token_kinds(logits.device) != kind[:, None], float("-inf")), cfg, gen)


def _kind_mass(logits: torch.Tensor, t_kind: float) -> torch.Tensor:
    """(B, V) logits -> (B, 3) probability of each token kind (EOS and the special tokens, block, offset) at
    temperature ``t_kind`` (0: 1, for the greedy choice)."""
    p = (logits / (t_kind or 1.0)).softmax(-1)
    return torch.stack([p[:, :vt.BLOCK0].sum(-1), p[:, vt.BLOCK0:vt.OFFSET0].sum(-1), p[:, vt.OFFSET0:].sum(-1)], -1)


def _nan_masked(logits: torch.Tensor) -> torch.Tensor:
    """(B, V) logits with NaN entries set to -inf: a token whose score is NaN is not drawn (sampling from NaN
    probabilities is an error, a device-side assert on CUDA); finite and infinite entries are kept as they are."""
    return torch.where(logits.isnan(), float("-inf"), logits)


_KINDS: dict[torch.device, torch.Tensor] = {}


def token_kinds(device: torch.device) -> torch.Tensor:
    """(VOCAB,) the kind of every token (``KIND_EOS`` for the special tokens), made once per device."""
    if device not in _KINDS:
        ids = torch.arange(vt.VOCAB_SIZE, device=device)
        _KINDS[device] = torch.where(ids < vt.BLOCK0, KIND_EOS, torch.where(ids < vt.OFFSET0, KIND_BLOCK, KIND_OFFSET))
    return _KINDS[device]


def pace_mask(through: torch.Tensor, prev: torch.Tensor, n_vert: torch.Tensor) -> torch.Tensor:
    """(B,) rows that may not stay in their block: the previous token was a vertex and the vertices emitted
    reach ``through`` + ``PACE_SLACK``, ``through`` being the evidence's ``expected_through(block, cfg.pace)``:
    ``cfg.pace`` x the cells' expected vertices up to this block, or a face-count target's share of them as it
    is (they may still end or go on to a later block, so the parts of the shape ahead are not cut off as a cap
    on the count would)."""
    return (prev >= vt.OFFSET0) & (n_vert >= through + PACE_SLACK)
