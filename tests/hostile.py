"""Hostile inputs shared by the bad-input tests and benchmarks/attack_memory.py."""

from __future__ import annotations

import json
import math
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


def _glb(doc: dict, binary: bytes) -> bytes:
    j = json.dumps(doc).encode()
    j += b" " * (-len(j) % 4)
    binary += b"\0" * (-len(binary) % 4)
    return (struct.pack("<4sII", b"glTF", 2, 28 + len(j) + len(binary)) + struct.pack("<I4s", len(j), b"JSON") + j
            + struct.pack("<I4s", len(binary), b"BIN\0") + binary)


def strided_accessor_glb(view_bytes: int = 1 << 20, accessors: int = 16, stride: int = 1) -> bytes:
    """One triangle, and ``accessors`` MAT4 accessors used by nothing over a ``view_bytes`` buffer view of
    ``byteStride`` ``stride``: the parser copies each out, 64 bytes per element, ``view_bytes - 63`` elements."""
    tri = struct.pack("<9f", 0, 0, 0, 1, 0, 0, 0, 1, 0)
    doc = {"asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0}],
           "meshes": [{"primitives": [{"attributes": {"POSITION": 0}}]}],
           "buffers": [{"byteLength": 36 + view_bytes}],
           "bufferViews": [{"buffer": 0, "byteOffset": 0, "byteLength": 36},
                           {"buffer": 0, "byteOffset": 36, "byteLength": view_bytes, "byteStride": stride}],
           "accessors": [{"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3",
                          "min": [0, 0, 0], "max": [1, 1, 0]}]
           + [{"bufferView": 1, "componentType": 5126, "count": view_bytes - 63, "type": "MAT4"}] * accessors}
    return _glb(doc, tri + b"\0" * view_bytes)


def obj_unspaced_faces(lines: int) -> bytes:
    """An OBJ whose faces are ``f1 2 3`` lines (no space after ``f``), which the parser takes as faces."""
    return b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n" + b"f1 2 3\n" * lines + b"f 1 2 3\n"


def gltf_empty_nodes(nodes: int) -> bytes:
    """A .gltf whose JSON is ``nodes`` empty objects: parsed whole, ~25x its size."""
    return b'{"asset":{"version":"2.0"},"nodes":[' + b"{}," * nodes + b"{}]}"


def ply_fans(faces: int, corners: int = 255) -> bytes:
    """A binary PLY of ``faces`` polygons of ``corners`` corners each: ``faces * (corners - 2)`` triangles."""
    head = (f"ply\nformat binary_little_endian 1.0\nelement vertex {corners}\nproperty float x\nproperty float y\n"
            f"property float z\nelement face {faces}\nproperty list uchar int vertex_indices\nend_header\n").encode()
    angles = [2 * math.pi * i / corners for i in range(corners)]
    verts = b"".join(struct.pack("<3f", math.cos(a), math.sin(a), 0.0) for a in angles)
    face = struct.pack("<B", corners) + struct.pack(f"<{corners}i", *range(corners))
    return head + verts + face * faces


def off_one_vertex_faces(faces: int) -> bytes:
    """An OFF file of ``faces`` faces on one vertex."""
    return f"OFF\n1 {faces} 0\n0 0 0\n".encode() + b"3 0 0 0\n" * faces


def heavy_obj() -> bytes:
    """A 9 MB OBJ within the default limits whose parse takes ~300 MB: over a small cap, under the default."""
    return b"v 0 0 0\nv 1 0 0\nv 0 1 0\n" + b"v 1 2 3\n" * 400_000 + b"f 1 2 3\n" * 900_000


def allocate(megabytes: int) -> int:
    """Allocate and touch ``megabytes`` MB (in a capped child: runs out of memory past its cap)."""
    block = bytearray(megabytes * 1024 * 1024)
    return len(block)


def sleep_for(seconds: float) -> float:
    import time

    time.sleep(seconds)
    return seconds


def die() -> None:
    import os

    os._exit(7)


def returns_an_object() -> object:
    """An answer that is not plain data (a class instance): the API process must refuse to unpickle it."""
    from pathlib import PurePosixPath

    return PurePosixPath("/etc/passwd")
