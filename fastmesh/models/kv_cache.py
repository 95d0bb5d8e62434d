"""An explicit key/value cache for incremental decoding.

Decoding is split in two phases (as in gpt-fast): *prefill* runs the whole prompt
(condition prefix + BOS) once and writes its keys/values at positions [0, T);
each *decode* step then runs one token per sequence at position ``pos`` and
attends to everything written so far.  Buffers are allocated once at full length,
so a step never reallocates.
"""

from __future__ import annotations

import torch


class KVCache:
    def __init__(self, n_layers: int, batch: int, heads: int, max_len: int, head_dim: int,
                 device: torch.device | str = "cpu", dtype: torch.dtype = torch.float32):
        shape = (n_layers, batch, heads, max_len, head_dim)
        self.k = torch.zeros(shape, device=device, dtype=dtype)
        self.v = torch.zeros(shape, device=device, dtype=dtype)
        self.max_len = max_len
        self.length = 0  # positions written so far

    def update(self, layer: int, pos: int, k: torch.Tensor, v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Write k, v (B, H, t, D) at [pos, pos + t) of ``layer``; return keys/values [0, pos + t)."""
        end = pos + k.shape[2]
        if end > self.max_len:
            raise IndexError(f"KV cache full: position {end} > {self.max_len}")
        self.k[layer, :, :, pos:end] = k.to(self.k.dtype)
        self.v[layer, :, :, pos:end] = v.to(self.v.dtype)
        if layer == self.k.shape[0] - 1:
            self.length = end
        return self.k[layer, :, :, :end], self.v[layer, :, :, :end]

    def select(self, index: torch.Tensor) -> None:
        """Keep only the sequences ``index`` (B',) — drops finished ones from a batch."""
        self.k = self.k[:, index]
        self.v = self.v[:, index]
