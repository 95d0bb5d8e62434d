"""Checks of a glTF upload (.gltf or .glb): its JSON's size, version, buffers, accessors and scene, counted with
every instance before the parser flattens anything."""

from __future__ import annotations

import json
import struct

from .shape import ShapeError

MAX_SCENE_NODES = 100_000  # glTF nodes walked when counting instances
# JSON objects and arrays in a glTF document: parsed, each takes ~25x its bytes (100,000 nodes take ~200,000).
MAX_JSON_CONTAINERS = 500_000
# Bytes of accessor data a glTF may make the parser materialise, per vertex and per face of the limits:
# position, normal, two texture coordinates, colour, tangent, joints and weights take ~100 per vertex.
ACCESSOR_BYTES_PER_VERTEX = 128
ACCESSOR_BYTES_PER_FACE = 12  # three 32-bit indices
GLTF_COMPONENTS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}
GLTF_COMPONENT_BYTES = {5120: 1, 5121: 1, 5122: 2, 5123: 2, 5125: 4, 5126: 4}
MIN_BYTE_STRIDE = 4  # the glTF 2.0 specification's minimum
GLB_MAGIC = b"glTF"


def gltf_json(data: bytes, ext: str) -> dict:
    """The glTF document of a .gltf (JSON) or .glb (its JSON chunk)."""
    if ext == "glb":
        if len(data) < 20 or data[:4] != GLB_MAGIC:
            raise ShapeError("unreadable", "not a binary glTF (GLB) file: it does not start with 'glTF'")
        length, kind = struct.unpack_from("<I4s", data, 12)
        if kind != b"JSON" or 20 + length > len(data):
            raise ShapeError("unreadable", "the GLB file is truncated or damaged: its JSON chunk is missing or "
                                           "shorter than declared")
        raw = data[20:20 + length]
    else:
        raw = data
    containers = raw.count(b"{") + raw.count(b"[")  # an upper bound: brackets inside strings count too
    if containers > MAX_JSON_CONTAINERS:
        raise ShapeError("too_large", f"the glTF document has {containers} JSON objects and arrays, over the limit "
                                      f"of {MAX_JSON_CONTAINERS}")
    try:
        doc = json.loads(raw)
    except (ValueError, RecursionError):
        raise ShapeError("unreadable", "a .gltf file must be JSON (use .glb for binary glTF)" if ext == "gltf"
                         else "the GLB file's JSON chunk is not valid JSON") from None
    if not isinstance(doc, dict):
        raise ShapeError("unreadable", "a glTF document must be a JSON object")
    return doc


def check_gltf(data: bytes, ext: str, max_points: int, max_faces: int) -> None:
    """glTF 2.0 only, embedded buffers only, and the scene's vertices counted with every instance.

    An external ``uri`` names a file this upload does not have (and must never be looked up on the
    server's disk).  Nodes instance meshes: a 150 KB file whose 1,200 nodes all show one mesh
    flattens to 1,200 copies, so vertices are counted per node before anything is flattened.
    """
    doc = gltf_json(data, ext)
    asset = doc.get("asset")
    version = str(asset.get("version", "")) if isinstance(asset, dict) else ""
    if not version.startswith("2"):
        raise ShapeError("unreadable", f"only glTF 2.0 is supported; this file says version '{version[:20]}'")
    buffers = doc.get("buffers")
    if not isinstance(buffers, (list, type(None))):
        raise ShapeError("unreadable", "glTF 'buffers' must be a list")
    for b in buffers or []:
        uri = b.get("uri") if isinstance(b, dict) else None
        if isinstance(uri, str) and not uri.startswith("data:"):
            raise ShapeError("unreadable", f"glTF buffer '{uri[:80]}' is an external file; upload a .glb, "
                                           "or a .gltf with embedded (data:) buffers")
    _check_accessors(doc, max_points, max_faces)
    verts, faces = _scene_counts(doc)
    if verts > max_points:
        raise ShapeError("too_large", f"the glTF scene holds {verts} vertices once its nodes' mesh instances are "
                                      f"counted, over the limit of {max_points}")
    if faces > max_faces:
        raise ShapeError("too_large", f"the glTF scene holds {faces} faces once its nodes' mesh instances are "
                                      f"counted, over the limit of {max_faces}")


def _check_accessors(doc: dict, max_points: int, max_faces: int) -> None:
    """Refuse strides under the specification's minimum and more accessor data than the limits need.

    The parser copies out every accessor, used by a mesh or not: a MAT4 accessor over a 1 MB buffer view
    with a 1-byte stride is a 64 MB array, so 16 of them in a 1 MB file would take a gigabyte.
    """
    views = _list(doc, "bufferViews")
    for i, view in enumerate(views):
        stride = view.get("byteStride") if isinstance(view, dict) else None
        if stride is not None and (not isinstance(stride, int) or stride < MIN_BYTE_STRIDE):
            raise ShapeError("unreadable", f"glTF bufferView {i} has byteStride {str(stride)[:20]}; the glTF 2.0 "
                                           f"specification requires at least {MIN_BYTE_STRIDE}")
    total = 0
    for a in _list(doc, "accessors"):
        if not isinstance(a, dict):
            continue
        count = a.get("count")
        width = GLTF_COMPONENTS.get(a.get("type"), 16) * GLTF_COMPONENT_BYTES.get(a.get("componentType"), 4)
        total += count * width if isinstance(count, int) and count > 0 else 0
    budget = max_points * ACCESSOR_BYTES_PER_VERTEX + max_faces * ACCESSOR_BYTES_PER_FACE
    if total > budget:
        raise ShapeError("too_large", f"the glTF file's accessors hold {total} bytes of data (used by a mesh or "
                                      f"not), over the {budget} bytes its vertex and face limits allow")


def _list(doc: dict, key: str) -> list:
    v = doc.get(key)
    return v if isinstance(v, list) else []


def _count(accessors: list, i) -> int:
    if isinstance(i, int) and 0 <= i < len(accessors) and isinstance(accessors[i], dict):
        c = accessors[i].get("count")
        return c if isinstance(c, int) and c > 0 else 0
    return 0


def _scene_counts(doc: dict) -> tuple[int, int]:
    """(vertices, faces) of the flattened scene: each mesh counted once per node path that shows it."""
    nodes = _list(doc, "nodes")
    per_mesh = _mesh_counts(doc)
    if len(nodes) > MAX_SCENE_NODES:
        raise ShapeError("too_large", f"the glTF scene has {len(nodes)} nodes, over the limit of {MAX_SCENE_NODES}")
    memo: dict[int, tuple[int, int]] = {}
    state: dict[int, int] = {}  # 1 = being counted (a cycle if met again), 2 = done
    total_v = total_f = 0
    for r in _scene_roots(doc, nodes):
        if isinstance(r, int) and 0 <= r < len(nodes):
            v, f = _subtree_counts(r, nodes, per_mesh, memo, state)
            total_v, total_f = total_v + v, total_f + f
    # Meshes no node shows may still be loaded: count each once at least.
    return max(total_v, sum(v for v, _ in per_mesh)), max(total_f, sum(f for _, f in per_mesh))


def _mesh_counts(doc: dict) -> list[tuple[int, int]]:
    """Per mesh of the document, (vertices, faces) of one instance of it."""
    accessors = _list(doc, "accessors")
    per_mesh = []
    for mesh in _list(doc, "meshes"):
        v = f = 0
        for prim in _list(mesh, "primitives") if isinstance(mesh, dict) else []:
            if not isinstance(prim, dict):
                continue
            attrs = prim.get("attributes")
            n = _count(accessors, attrs.get("POSITION")) if isinstance(attrs, dict) else 0
            v += n
            f += (_count(accessors, prim["indices"]) if "indices" in prim else n) // 3
        per_mesh.append((v, f))
    return per_mesh


def _scene_roots(doc: dict, nodes: list) -> list:
    """The root nodes of the scene shown: the document's ``scene`` (default 0), else every node no node holds."""
    scenes = _list(doc, "scenes")
    pick = doc.get("scene", 0)
    if scenes and isinstance(pick, int) and 0 <= pick < len(scenes) and isinstance(scenes[pick], dict):
        return _list(scenes[pick], "nodes")
    children = {c for n in nodes if isinstance(n, dict) for c in _list(n, "children")}
    return [i for i in range(len(nodes)) if i not in children]


def _subtree_counts(i: int, nodes: list, per_mesh: list[tuple[int, int]], memo: dict[int, tuple[int, int]],
                    state: dict[int, int]) -> tuple[int, int]:
    """(vertices, faces) under node ``i``, its own mesh included; ``memo`` and ``state`` are shared across roots.

    An iterative post-order walk: a deep chain of children must not exhaust Python's stack.
    """
    stack = [(i, False)]
    while stack:
        k, expanded = stack.pop()
        if state.get(k) == 2:
            continue
        node = nodes[k] if isinstance(nodes[k], dict) else {}
        kids = [c for c in _list(node, "children") if isinstance(c, int) and 0 <= c < len(nodes)]
        if not expanded:
            if state.get(k) == 1:
                continue
            state[k] = 1
            stack.append((k, True))
            for c in kids:
                if state.get(c) == 1:
                    raise ShapeError("unreadable", "the glTF node hierarchy has a cycle (a node is its own ancestor)")
                stack.append((c, False))
            continue
        m = node.get("mesh")
        v, f = per_mesh[m] if isinstance(m, int) and 0 <= m < len(per_mesh) else (0, 0)
        for c in kids:
            cv, cf = memo[c]
            v, f = v + cv, f + cf
        memo[k], state[k] = (v, f), 2
    return memo[i]
