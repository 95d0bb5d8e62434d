"""Tokenizers: FastMesh's vertex tokenizer, and vanilla / BPT whole-mesh baselines."""

from . import bpt, vanilla, vertex
from .quantize import LEVELS, clean_faces, dequantize, quantize, quantize_mesh, sort_key

__all__ = ["LEVELS", "bpt", "vanilla", "clean_faces", "dequantize", "quantize", "quantize_mesh", "sort_key", "vertex"]
