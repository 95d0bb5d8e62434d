"""Hostile inputs shared by the bad-input tests and benchmarks/attack_memory.py."""

from __future__ import annotations

import json
import struct

import trimesh


def instanced_glb(nodes: int, subdivisions: int = 3) -> bytes:
    """A GLB holding one icosphere mesh shown by ``nodes`` nodes: flattened, each node is one more copy."""
    glb = trimesh.creation.icosphere(subdivisions).export(file_type="glb")
    (jlen,) = struct.unpack_from("<I", glb, 12)
    doc = json.loads(glb[20:20 + jlen])
    mesh = next(n["mesh"] for n in doc["nodes"] if "mesh" in n)
    doc["nodes"] = [{"mesh": mesh, "translation": [3.0 * i, 0.0, 0.0]} for i in range(nodes)]
    doc["scenes"], doc["scene"] = [{"nodes": list(range(nodes))}], 0
    j = json.dumps(doc).encode()
    j += b" " * (-len(j) % 4)
    rest = glb[20 + jlen:]
    return (struct.pack("<4sII", b"glTF", 2, 20 + len(j) + len(rest)) + struct.pack("<I4s", len(j), b"JSON") + j
            + rest)
