"""Checks of an upload's declared sizes and structure, before a parser allocates anything (OBJ, STL and OFF
here; PLY in :mod:`.ply_check`, glTF in :mod:`.gltf_check`).

A file's header can declare far more data than the file holds (a PLY vertex count, a glTF scene
that instances one mesh on thousands of nodes, an OBJ of millions of short lines).  Parsers
allocate what is declared, so these checks count first and refuse with a :class:`ShapeError`
that names the problem in the user's terms.  :func:`plain_parse_error` words the errors that
get past them (raised by trimesh or numpy) for a person.
"""

from __future__ import annotations

import re
import struct

import numpy as np

from .ply_check import MAX_PLY_HEADER, ply_length_error, unused_elements
from .shape import ShapeError, too_many
from .sniff import STL_HEADER, STL_TRIANGLE, not_obj

FORMAT_NAMES = {"obj": "Wavefront OBJ", "glb": "binary glTF (GLB)", "gltf": "glTF JSON", "ply": "PLY",
                "stl": "STL", "off": "OFF", "xyz": "text point", "txt": "text point", "npy": "NumPy .npy",
                "npz": "NumPy .npz"}
# What one point and one face may take in a text file of each format, as (lines, values): an OBJ vertex with its
# ``vt`` and ``vn`` lines (11 words), a PLY vertex with normal, colour and UV (12), a face with its colour, an ASCII
# STL facet (7 lines, 21 words).  Parsing time and memory follow the lines and values, used or not.
TEXT_COST = {"obj": ((3, 11), (1, 4)), "ply": ((1, 12), (1, 8)), "off": ((1, 7), (1, 8)), "stl": ((0, 0), (7, 21)),
             "xyz": ((1, 6), (0, 0)), "txt": ((1, 6), (0, 0))}
SPARE_LINES, SPARE_VALUES = 1_000, 10_000  # a header, comments, groups and materials on top
WORD_CHUNK = 1 << 22  # bytes counted at once (bounds the count's memory)


# --------------------------------------------------------------------------- parse cost of text files


def parse_budget(ext: str, max_points: int, max_faces: int) -> tuple[int, int]:
    """``(lines, values)`` a text file of format ``ext`` may hold: what ``max_points`` points and ``max_faces``
    faces take at most in it (:data:`TEXT_COST`), and a spare for headers and comments."""
    (p_lines, p_values), (f_lines, f_values) = TEXT_COST[ext]
    return (max_points * p_lines + max_faces * f_lines + SPARE_LINES,
            max_points * p_values + max_faces * f_values + SPARE_VALUES)


def count_lines(data: bytes) -> int:
    """Lines of a text, ended by \\n, \\r\\n or \\r (the last one unended or not)."""
    unended = bool(data) and not data.endswith((b"\n", b"\r"))
    return data.count(b"\n") + data.count(b"\r") - data.count(b"\r\n") + unended


def count_words(data: bytes) -> int:
    """Runs of bytes other than ASCII whitespace (space, \\t, \\n, \\v, \\f, \\r): the words ``bytes.split`` makes,
    what a text parser splits a file into."""
    total, after_space = 0, True
    view = memoryview(data)
    for lo in range(0, len(data), WORD_CHUNK):
        block = np.frombuffer(view[lo:lo + WORD_CHUNK], np.uint8)
        space = (block == 32) | ((block >= 9) & (block <= 13))
        start = ~space
        start[1:] &= space[:-1]
        start[0] &= after_space
        total += int(np.count_nonzero(start))
        after_space = bool(space[-1])
    return total


def _is_text(data: bytes, ext: str) -> bool:
    """Whether a mesh parser reads ``data`` as text: an OBJ, an OFF, an ASCII PLY or STL (a text point file's reader
    counts its own lines: ``pointfiles.load_text_points``)."""
    if ext == "ply":
        return re.search(rb"^format\s+ascii", data[:MAX_PLY_HEADER], re.M) is not None
    if ext == "stl":  # ASCII when it starts with 'solid' and has not the length of a binary one (check_stl)
        count = struct.unpack("<I", data[80:STL_HEADER])[0] if len(data) >= STL_HEADER else -1
        return data.lstrip()[:5].lower() == b"solid" and len(data) != STL_HEADER + STL_TRIANGLE * count
    return ext in ("obj", "off")


def check_parse_cost(data: bytes, ext: str, max_points: int, max_faces: int) -> None:
    """Refuse a text file with more lines or values than a file within the limits holds (:func:`parse_budget`),
    counting every line and value, also those the shape does not use (comments, texture coordinates, a PLY
    element other than vertices and faces): a parser reads them all, and their time and memory are spent before
    any count of points or faces could refuse the file."""
    if not _is_text(data, ext):
        return
    name = FORMAT_NAMES.get(ext, ext)
    max_lines, max_values = parse_budget(ext, max_points, max_faces)
    unused = unused_elements(data) if ext == "ply" else ""
    why = (f" ({unused} not used)" if unused else "") + \
        f"; a {name} file may hold what {max_points} points and {max_faces} faces take"
    lines = count_lines(data)
    if lines > max_lines:
        raise ShapeError("too_large", f"the {name} file has {lines} lines to read, over the limit of {max_lines} "
                                      f"lines{why}")
    values = count_words(data)
    if values > max_values:
        raise ShapeError("too_large", f"the {name} file has {values} values to read, over the limit of {max_values} "
                                      f"values{why}")


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
