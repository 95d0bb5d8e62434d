"""Checks of an upload's declared sizes and structure, before a parser allocates anything.

A file's header can declare far more data than the file holds (a PLY vertex count, a glTF scene
that instances one mesh on thousands of nodes, an OBJ of millions of short lines).  Parsers
allocate what is declared, so these checks count first and refuse with a :class:`ShapeError`
that names the problem in the user's terms.  :func:`plain_parse_error` words the errors that
get past them (raised by trimesh or numpy) for a person.
"""

from __future__ import annotations

import json
import re
import struct

from .shape import ShapeError, too_many
from .sniff import STL_HEADER, STL_TRIANGLE, not_obj

FORMAT_NAMES = {"obj": "Wavefront OBJ", "glb": "binary glTF (GLB)", "gltf": "glTF JSON", "ply": "PLY",
                "stl": "STL", "off": "OFF", "xyz": "text point", "txt": "text point", "npy": "NumPy .npy",
                "npz": "NumPy .npz"}
PLY_SIZES = {"char": 1, "int8": 1, "uchar": 1, "uint8": 1, "short": 2, "int16": 2, "ushort": 2, "uint16": 2,
             "int": 4, "int32": 4, "uint": 4, "uint32": 4, "float": 4, "float32": 4, "double": 8, "float64": 8}
PLURALS = {"vertex": "vertices", "face": "faces", "edge": "edges"}
MAX_PLY_HEADER = 64 * 1024  # bytes; a real header is a few hundred
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


# --------------------------------------------------------------------------- OBJ


def check_obj(data: bytes, max_points: int, max_faces: int) -> None:
    """Count vertex and face lines (parsing 64 MB of them takes ~1 GB), then the faces' triangles.  The parser
    takes every line that starts with ``f`` as a face (``f1 2 3``, ``f\t1 2 3``), and fans each polygon."""
    n_v = data.count(b"\nv ") + data.startswith(b"v ")
    if n_v > max_points:
        raise too_many(n_v, max_points)
    n_f = data.count(b"\nf") + data.startswith(b"f")
    if n_f > max_faces:
        raise too_many(n_f, max_faces, "faces")
    if n_f:  # a face of k corners is fanned into k - 2 triangles: ~0.4 s for a million face lines
        triangles = sum(max(len(line[1:].split()) - 2, 0) for line in re.findall(rb"^f[^\n]*", data, re.M))
        if triangles > max_faces:
            raise ShapeError("too_large", f"the OBJ file's {n_f} faces are {triangles} triangles, over the limit "
                                          f"of {max_faces} faces")
    if n_v == 0 and (why := not_obj(data)):  # a text of another kind renamed .obj: unreadable, not empty
        raise ShapeError("unreadable", why)


# --------------------------------------------------------------------------- STL


def check_stl(data: bytes, max_faces: int) -> None:
    """A binary STL is exactly its 84-byte header and 50 bytes per triangle it declares (its parser takes any
    other file for ASCII STL, which starts with ``solid``): refuse more triangles than ``max_faces``, and a
    file that is neither, such as a text of another kind renamed .stl."""
    count = struct.unpack("<I", data[80:STL_HEADER])[0] if len(data) >= STL_HEADER else None
    if count is not None and len(data) == STL_HEADER + STL_TRIANGLE * count:
        if count > max_faces:
            raise too_many(count, max_faces, "faces")
        return
    if data.lstrip()[:5].lower() == b"solid":
        return
    size = (f"is {len(data)} bytes, shorter than the 84-byte header of a binary STL" if count is None else
            f"does not have the length its binary header declares ({count} triangles, "
            f"{STL_HEADER + STL_TRIANGLE * count} bytes; the file has {len(data)})")
    raise ShapeError("unreadable", f"not an STL file: it does not start with 'solid' (ASCII STL) and {size}")


# --------------------------------------------------------------------------- OFF


def check_off(data: bytes, max_points: int, max_faces: int) -> None:
    """Refuse declared vertex and face counts over the limits (the parser splits every line of the file
    into Python strings first: ~25x the file)."""
    words: list[bytes] = []
    for line in data[:MAX_PLY_HEADER].splitlines():
        line = line.split(b"#", 1)[0].strip()
        if line:
            words += line.split()
        if len(words) >= 4:
            break
    if not words or not words[0].upper().endswith(b"OFF"):
        raise ShapeError("unreadable", "the OFF file's first line must be 'OFF' and the next the vertex, face "
                                       "and edge counts")
    counts = words[1:3]
    if len(counts) < 2 or not all(c.isdigit() for c in counts):
        raise ShapeError("unreadable", "the OFF file's counts line must hold the vertex, face and edge counts")
    n_v, n_f = int(counts[0]), int(counts[1])
    if n_v > max_points:
        raise too_many(n_v, max_points)
    if n_f > max_faces:
        raise too_many(n_f, max_faces, "faces")


# --------------------------------------------------------------------------- PLY


def _ply_header(data: bytes) -> tuple[str, list[tuple[str, int, list[tuple]]], int]:
    """``(format, [(element, count, properties)], header length)``; properties are ``(type,)`` or
    ``("list", count type, item type)``."""
    end = re.search(rb"end_header\r?\n", data[:MAX_PLY_HEADER])
    if not data.startswith(b"ply") or end is None:
        raise ShapeError("unreadable", "PLY header is incomplete: no 'end_header' line within the first "
                                       f"{MAX_PLY_HEADER // 1024} KB")
    fmt, elements = "", []
    for raw in data[:end.start()].decode("ascii", "replace").splitlines():
        words = raw.split()
        if not words:
            continue
        if words[0] == "format" and len(words) >= 2:
            fmt = words[1]
        elif words[0] == "element":
            if len(words) != 3 or not words[2].isdigit():
                raise ShapeError("unreadable", f"PLY header line '{raw[:60]}' should be 'element <name> <count>'")
            elements.append((words[1], int(words[2]), []))
        elif words[0] == "property":
            if not elements:
                raise ShapeError("unreadable", f"PLY header line '{raw[:60]}' comes before any 'element' line")
            prop = ("list", words[2], words[3]) if len(words) >= 5 and words[1] == "list" else (words[1],) \
                if len(words) >= 3 else None
            if prop is None:
                raise ShapeError("unreadable", f"PLY header line '{raw[:60]}' should be 'property <type> <name>'")
            for kind in prop[1:] if prop[0] == "list" else prop:
                if kind not in PLY_SIZES:
                    raise ShapeError("unreadable", f"PLY header line '{raw[:60]}' names type '{kind[:20]}'; PLY "
                                                   f"types are {', '.join(PLY_SIZES)}")
            elements[-1][2].append(prop)
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise ShapeError("unreadable", f"PLY header names format '{fmt[:30]}'; expected ascii, "
                                       "binary_little_endian or binary_big_endian")
    return fmt, elements, end.end()


def check_ply(data: bytes, max_points: int, max_faces: int) -> None:
    """Refuse declared counts over the limits, and binary bodies shorter than their header declares."""
    fmt, elements, start = _ply_header(data)
    counts = {name: n for name, n, _ in elements}
    if counts.get("vertex", 0) > max_points:
        raise too_many(counts["vertex"], max_points)
    if counts.get("face", 0) > max_faces:
        raise too_many(counts["face"], max_faces, "faces")
    if fmt == "ascii":
        return
    need, _ = _ply_bytes(elements)
    have = len(data) - start
    if have < need:
        raise ShapeError("unreadable", f"the PLY file is truncated: its header declares {_declared(elements)}, "
                                       f"at least {need} bytes of binary data, but only {have} bytes follow "
                                       "the header")
    triangles = _ply_triangles(data, fmt, elements, start, max_faces)
    if triangles > max_faces:
        raise ShapeError("too_large", f"the PLY file's {counts.get('face', 0)} faces are {triangles} triangles, "
                                      f"over the limit of {max_faces} faces")


def _ply_triangles(data: bytes, fmt: str, elements, start: int, max_faces: int) -> int:
    """Triangles of a binary PLY's faces once each polygon of k corners is fanned into k - 2.

    The bytes after the fixed-size elements bound the corners from above; only when that bound is over
    ``max_faces`` are the faces' corner counts read one by one (and the exact count returned).
    """
    offset, faces = start, None
    for name, n, props in elements:
        if name == "face":
            faces = (n, props)
            break
        if any(p[0] == "list" for p in props):
            return 0  # a list before the faces: their offset is unknown without parsing; the parser counts
        offset += n * sum(PLY_SIZES[p[0]] for p in props)
    if faces is None or not faces[1] or faces[1][0][0] != "list" or len(faces[1]) != 1:
        return 0  # faces with other properties too: the parser's triangles are counted after it
    n, ((_, count_type, item_type),) = faces
    csize, isize = PLY_SIZES[count_type], PLY_SIZES[item_type]
    bound = (len(data) - offset - n * csize) // isize - 2 * n  # every byte left being a corner
    return bound if bound <= max_faces else _walk_fans(data, offset, n, csize, isize, fmt == "binary_big_endian")


def _walk_fans(data: bytes, offset: int, n: int, csize: int, isize: int, big: bool) -> int:
    """Sum of (corners - 2) over ``n`` face records ``<count><count items>`` from ``offset``."""
    end = "big" if big else "little"
    triangles = 0
    for _ in range(n):
        if offset + csize > len(data):
            break
        k = int.from_bytes(data[offset:offset + csize], end, signed=False)
        triangles += max(k - 2, 0)
        offset += csize + k * isize
    return triangles


def _ply_bytes(elements) -> tuple[int, int]:
    """Body size of a binary PLY: (at least, with every list empty; when every list holds 3 items)."""
    least = triangles = 0
    for _, n, props in elements:
        for p in props:
            kind = p[1] if p[0] == "list" else p[0]
            size = PLY_SIZES[kind]  # _ply_header refused unknown types
            item = PLY_SIZES[p[2]] if p[0] == "list" else 0
            least += n * size
            triangles += n * (size + 3 * item)
    return least, triangles


def _declared(elements) -> str:
    return ", ".join(f"{n} {PLURALS.get(name, name + 's') if n != 1 else name}" for name, n, _ in elements)


def ply_length_error(data: bytes) -> str:
    """Words for a binary PLY whose body does not match its header (trimesh's 'PLY is unexpected length!')."""
    try:
        _, elements, start = _ply_header(data)
    except ShapeError as e:
        return e.message
    have = len(data) - start
    _, triangles = _ply_bytes(elements)
    expect = f" ({triangles} bytes if its faces are triangles)" if triangles else ""
    return (f"the PLY file's data does not match its header: the header declares {_declared(elements)}{expect}, "
            f"but {have} bytes follow it; the file is truncated, or its counts are wrong")


# --------------------------------------------------------------------------- glTF


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
    accessors, nodes = _list(doc, "accessors"), _list(doc, "nodes")
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
    if len(nodes) > MAX_SCENE_NODES:
        raise ShapeError("too_large", f"the glTF scene has {len(nodes)} nodes, over the limit of {MAX_SCENE_NODES}")
    memo: dict[int, tuple[int, int]] = {}
    state: dict[int, int] = {}  # 1 = being counted (a cycle if met again), 2 = done

    def count(i: int) -> tuple[int, int]:
        # Iterative post-order walk: a deep chain of children must not exhaust Python's stack.
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
                        raise ShapeError("unreadable", "the glTF node hierarchy has a cycle (a node is its own "
                                                       "ancestor)")
                    stack.append((c, False))
                continue
            m = node.get("mesh")
            v, f = per_mesh[m] if isinstance(m, int) and 0 <= m < len(per_mesh) else (0, 0)
            for c in kids:
                cv, cf = memo[c]
                v, f = v + cv, f + cf
            memo[k], state[k] = (v, f), 2
        return memo[i]

    children = {c for n in nodes if isinstance(n, dict) for c in _list(n, "children")}
    scenes = _list(doc, "scenes")
    pick = doc.get("scene", 0)
    roots = None
    if scenes and isinstance(pick, int) and 0 <= pick < len(scenes) and isinstance(scenes[pick], dict):
        roots = _list(scenes[pick], "nodes")
    if roots is None:
        roots = [i for i in range(len(nodes)) if i not in children]
    total_v = total_f = 0
    for r in roots:
        if isinstance(r, int) and 0 <= r < len(nodes):
            v, f = count(r)
            total_v, total_f = total_v + v, total_f + f
    # Meshes no node shows may still be loaded: count each once at least.
    return max(total_v, sum(v for v, _ in per_mesh)), max(total_f, sum(f for _, f in per_mesh))


# --------------------------------------------------------------------------- parser errors in words


def plain_parse_error(exc: Exception, ext: str, data: bytes) -> str:
    """A parser's exception (trimesh, numpy, struct, zipfile) as a sentence a person can act on."""
    name = FORMAT_NAMES.get(ext, f".{ext}")
    text = str(exc)
    if ext == "ply" and "unexpected length" in text:
        return ply_length_error(data)
    eof = re.match(r"EOF: reading array data, expected (\d+) bytes got (\d+)", text)
    if eof:
        return (f"the {name} file is truncated: its header declares {eof[1]} bytes of array data, but only "
                f"{eof[2]} are present")
    if "chunk was not expected length" in text:
        return f"the {name} file is truncated or damaged: a chunk is shorter or longer than its header declares"
    if isinstance(exc, UnicodeDecodeError):
        return f"the {name} file contains bytes that are not text where text is expected"
    if ext in ("npy", "npz"):
        if "pickle" in text.lower():
            return f"the {name} file holds Python objects; only plain numeric arrays are accepted"
        if "zip" in text.lower() or "magic" in text.lower():
            return f"not a {name} file (its signature is missing or damaged)"
        return f"the {name} file's array header is damaged (it does not say the array's shape and type clearly)"
    if ext == "off" and "count line" in text:
        return "the OFF file's first line must be 'OFF' and the next the vertex, face and edge counts"
    if isinstance(exc, (struct.error, EOFError)) or "buffer is too small" in text or "ran out of data" in text:
        return f"the {name} file ends before the data its header declares (it is truncated, or its counts are wrong)"
    if "cannot reshape array" in text or "inhomogeneous" in text or "with a sequence" in text \
            or "values to unpack" in text:
        return (f"lines of the {name} file hold the wrong number of values (a vertex needs x y z, a face at least "
                "3 vertex indices), or the file is cut short")
    if "could not be read to its end" in text or "could not convert" in text or "invalid literal" in text:
        return f"the {name} file has a value that is not a number where a number is expected, or a line cut short"
    if isinstance(exc, (IndexError, KeyError)):
        return f"the {name} file refers to an element, property or index it does not define (it is damaged)"
    return f"the file is not a readable {name} file (it is damaged, truncated or of another format)"
