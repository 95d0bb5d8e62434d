"""Sampling on the device from counter-based noise: reproducible, with no generator state and no host copy.

``generate.choose_next`` draws with ``torch.multinomial`` from one ``torch.Generator`` per row: the draw
reads and advances the generator's state, which a captured CUDA graph cannot replay, and checking the
logits for NaN reads a value back to the host every token.  Here every draw is a Gumbel-max,

    token = argmax_i (log p_i + G_i),    G_i = -log(-log(u_i)),

which picks token i with probability p_i, and u_i is a hash of (the row's seed, the step, the stream, i):
a pure function of integers, so the same on every device, in any batch, in a graph or not, and a row's
draws do not depend on the other rows.  The hash is Chris Wellons' ``lowbias32`` on 32-bit values held
in int64 tensors: some twenty integer kernels a draw.

The two steps of ``choose_next`` are kept (the token's kind at ``structure_temperature``, then the token
of that kind at ``temperature`` with top-k / top-p and the cell weight on the offsets), with the same
masked logits: at temperature 0 both are the same argmax, token for token.
"""

from __future__ import annotations

import torch

from ..params import SamplingConfig
from ..tokenizer import vertex as vt
from .choice import _kind_mass, _nan_masked, token_kinds, token_probs

MASK32 = 0xFFFFFFFF
STREAM_KIND, STREAM_TOKEN = 0, 1  # the two draws of a step
_IDS: dict[torch.device, torch.Tensor] = {}  # device -> (2, VOCAB) hash of every token id per stream


def hash32(x):
    """lowbias32 of 32-bit values (a Python int or an int64 tensor of values in ``[0, 2^32)``).

    A product of two 32-bit values can pass 2^63 and wrap in int64; its low 32 bits, all that is kept, are
    the same (two's complement, on every device), and a Python int keeps them exactly.
    """
    x = x ^ (x >> 16)
    x = (x * 0x7FEB352D) & MASK32
    x = x ^ (x >> 15)
    x = (x * 0x846CA68B) & MASK32
    return x ^ (x >> 16)


def seed_key(seed: int) -> int:
    """A row's 32-bit key from its int64 ``seed`` (both halves mixed)."""
    return hash32((seed & MASK32) ^ hash32(((seed >> 32) & MASK32) ^ 0x9E3779B9))


def _token_hashes(device: torch.device) -> torch.Tensor:
    """(2, VOCAB) a hash of every token id, one row per stream."""
    if device not in _IDS:
        ids = torch.arange(vt.VOCAB_SIZE, device=device, dtype=torch.long)
        _IDS[device] = torch.stack([hash32(ids ^ 0x85EBCA6B), hash32(ids ^ 0xC2B2AE35)])
    return _IDS[device]


def gumbel(keys: torch.Tensor, step: torch.Tensor, stream: int, ids: torch.Tensor) -> torch.Tensor:
    """Gumbel noise of B rows at one step, one value per id: ``-log(-log(u))``, ``u`` from the hash of the row's
    key, the step, the stream and the id.

    Parameters
    ----------
    keys : (B,) int64 row keys (``seed_key``).
    step : (1,) int64 step counter (a tensor, so a captured graph reads its current value), or (B,).
    stream : which draw of the step (``STREAM_KIND`` or ``STREAM_TOKEN``).
    ids : (B, n) or (n,) int64 token ids in ``[0, VOCAB)``.

    Returns
    -------
    (B, n) float32.
    """
    s = hash32((keys + step * 0x9E3779B9) & MASK32)  # the row's value at this step (Weyl sequence, then mixed)
    h = hash32(s[:, None] ^ _token_hashes(keys.device)[stream][ids])
    u = ((h >> 8).float() + 0.5) * (1.0 / (1 << 24))  # in (0, 1), 24 bits: exact in float32
    return -torch.log(-torch.log(u))


def sample_static(logits: torch.Tensor, cfg: SamplingConfig, keys: torch.Tensor, step: torch.Tensor
                  ) -> torch.Tensor:
    """(B, V) masked logits -> (B,) token ids: ``generate.sample_next`` with a Gumbel-max draw."""
    if cfg.temperature == 0:
        return logits.argmax(-1)
    probs, ids = token_probs(logits, cfg)
    pick = (probs.log() + gumbel(keys, step, STREAM_TOKEN, ids)).argmax(-1, keepdim=True)
    return ids.gather(-1, pick).squeeze(-1)


def choose_static(logits: torch.Tensor, cfg: SamplingConfig, keys: torch.Tensor, step: torch.Tensor,
                  offset_bias: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """(B, V) masked logits -> (B,) token ids and (B,) bool rows that allow no token, ``generate.choose_next``'s
    two steps drawn with :func:`gumbel`.

    NaN logits are dropped (never drawn), on the device; a row left with no finite logit is reported, not
    raised, so the caller checks it when it next reads anything back.
    """
    logits = _nan_masked(logits)
    t_kind = cfg.structure_temperature if cfg.temperature > 0 else 0.0
    mass = _kind_mass(logits, t_kind)
    if t_kind > 0:
        kinds = torch.arange(3, device=logits.device)
        kind = (mass.log() + gumbel(keys, step, STREAM_KIND, kinds)).argmax(-1)
    else:
        kind = mass.argmax(-1)
    if offset_bias is not None:
        logits = torch.cat([logits[:, :vt.OFFSET0], logits[:, vt.OFFSET0:] + offset_bias], dim=-1)
    logits = logits.masked_fill(token_kinds(logits.device) != kind[:, None], float("-inf"))
    stuck = ~torch.isfinite(logits).any(-1)
    return sample_static(logits, cfg, keys, step), stuck
