"""Checks of a PLY upload's header and binary body before the parser allocates what the header declares."""

from __future__ import annotations

import re

from .shape import ShapeError, too_many

PLY_SIZES = {"char": 1, "int8": 1, "uchar": 1, "uint8": 1, "short": 2, "int16": 2, "ushort": 2, "uint16": 2,
             "int": 4, "int32": 4, "uint": 4, "uint32": 4, "float": 4, "float32": 4, "double": 8, "float64": 8}
PLURALS = {"vertex": "vertices", "face": "faces", "edge": "edges"}
MAX_PLY_HEADER = 64 * 1024  # bytes; a real header is a few hundred


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


def unused_elements(data: bytes) -> str:
    """The elements of a PLY file other than its vertices and faces, as ``"element 'junk' (148148 rows)"``
    ("" for none, or for a header that does not read)."""
    try:
        _, elements, _ = _ply_header(data)
    except ShapeError:
        return ""
    named = [f"'{name[:30]}' ({n} rows)" for name, n, _ in elements if name not in ("vertex", "face") and n]
    return f"element{'s' if len(named) > 1 else ''} {', '.join(named)}" if named else ""


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
