"""Tokenizers: FastMesh's vertex tokenizer, and vanilla / BPT whole-mesh baselines, on the 7-bit grid (``grid``)."""

from . import bpt, grid, vanilla, vertex
from .grid import LEVELS, dequantize, quantize, sort_key
from .quantize import clean_faces, quantize_mesh

__all__ = ["LEVELS", "bpt", "grid", "vanilla", "clean_faces", "dequantize", "quantize", "quantize_mesh", "sort_key",
           "vertex"]
