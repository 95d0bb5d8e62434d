"""Minimal PNG encoder on the standard library (zlib + struct).

Why not Pillow: the previews only ever need "8-bit RGB(A) array -> PNG bytes", which is
~30 lines on zlib, while Pillow would be a new compiled dependency for every install (the
worker, the API, CI) just for that.  Decoding is not needed by the service.
"""

from __future__ import annotations

import struct
import zlib

import numpy as np


def to_png(image, compress_level: int = 6) -> bytes:
    """Encode an 8-bit grey, RGB or RGBA image as PNG bytes (stdlib zlib, no imaging library).

    Each row uses the "Up" filter when the whole image compresses better that way
    (it usually does for smooth shading); otherwise no filter.

    Parameters
    ----------
    image : (H, W), (H, W, 1), (H, W, 3) or (H, W, 4) uint8
    compress_level : int
        zlib level 0-9.
    """
    img = np.asarray(image)
    if img.dtype != np.uint8:
        raise ValueError(f"image must be uint8, got {img.dtype}")
    if img.ndim == 2:
        img = img[:, :, None]
    if img.ndim != 3 or img.shape[2] not in (1, 3, 4) or img.shape[0] == 0 or img.shape[1] == 0:
        raise ValueError(f"image must be (H, W), (H, W, 1|3|4), got {img.shape}")
    h, w, c = img.shape
    rows = img.reshape(h, w * c)
    up = rows.copy()
    up[1:] -= rows[:-1]  # uint8 wrap-around is exactly PNG's modulo-256 filter arithmetic
    best = None
    for ftype, data in ((0, rows), (2, up)):
        raw = np.concatenate([np.full((h, 1), ftype, dtype=np.uint8), data], axis=1).tobytes()
        comp = zlib.compress(raw, compress_level)
        if best is None or len(comp) < len(best):
            best = comp
    color_type = {1: 0, 3: 2, 4: 6}[c]
    header = struct.pack(">IIBBBBB", w, h, 8, color_type, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", header) + _chunk(b"IDAT", best) + _chunk(b"IEND", b"")


def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)
