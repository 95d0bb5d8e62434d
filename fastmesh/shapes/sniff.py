"""The format of a shape file: its name's extension, or for bytes given without a name, its first bytes.

Each format that can be recognised by content is: the binary ones by their signature (glTF, NumPy, zip,
PLY), OFF by its first word, binary STL by its declared size, and text by its first line (a Wavefront OBJ
statement, or 3 or 6 numbers of a point file).  Anything else is left to the caller to name.
"""

from __future__ import annotations

import struct
from pathlib import Path

from .shape import SUPPORTED_FORMATS, ShapeError

SNIFF_BYTES = 64 * 1024  # read of a text file to find its first line that is not a comment
# Wavefront OBJ statements (geometry, grouping, display and free-form); a line starting with another word is
# not OBJ.
OBJ_STATEMENTS = frozenset(
    b"v vt vn vp f l p o g s mg mtllib usemtl cstype deg bmat step curv curv2 surf parm trim hole scrv sp end "
    b"con bevel c_interp d_interp lod shadow_obj trace_obj ctech stech call csh maplib usemap".split())
STL_HEADER, STL_TRIANGLE = 84, 50  # bytes: binary STL's header and triangle count, and each triangle


def file_format(data: bytes, name: str) -> str:
    """The format of a file: its name's extension, or for bytes without a name (``name`` empty) what their
    content says (:func:`sniff_format`).

    Raises
    ------
    ShapeError
        ``unsupported_format``, saying what to do: no extension, an extension of no supported format, or bytes
        whose content does not say.
    """
    kinds = ", ".join(SUPPORTED_FORMATS)
    if not name:
        ext = sniff_format(data)
        if ext is None:
            raise ShapeError("unsupported_format", "cannot tell the format of these bytes from their content; name "
                                                   "it: load_shape(data, filename='shape.obj'), with one of "
                                                   f"{kinds}")
        return ext
    ext = Path(name).suffix.lower().lstrip(".")
    if not ext:
        raise ShapeError("unsupported_format", f"'{Path(name).name}' has no extension to tell its format; "
                                               f"name the file with one of {kinds}")
    if ext not in SUPPORTED_FORMATS:
        raise ShapeError("unsupported_format", f"unsupported file type '.{ext}'; use one of {kinds}")
    return ext


def first_statement(data: bytes) -> tuple[int, list[bytes]] | None:
    """``(line number, words)`` of the first line of a text file that is neither blank nor a ``#`` comment,
    among its first :data:`SNIFF_BYTES`; None when there is none there."""
    head = data[:SNIFF_BYTES]
    for number, raw in enumerate(head.replace(b"\r\n", b"\n").replace(b"\r", b"\n").split(b"\n"), 1):
        words = raw.replace(b",", b" ").split()
        if words and not words[0].startswith(b"#"):
            return number, words
    return None


def _numbers(words: list[bytes]) -> bool:
    try:
        [float(w) for w in words]
    except ValueError:
        return False
    return True


def sniff_format(data: bytes) -> str | None:
    """The extension (``obj``, ``glb``, ``gltf``, ``ply``, ``stl``, ``off``, ``xyz``, ``npy``, ``npz``) whose
    format ``data`` is in, or None when its content does not say."""
    if data.startswith(b"glTF"):
        return "glb"
    if data.startswith(b"\x93NUMPY"):
        return "npy"
    if data.startswith(b"PK\x03\x04"):
        return "npz"
    if data[:4] in (b"ply\n", b"ply\r"):
        return "ply"
    if data.lstrip()[:5].lower() == b"solid":
        return "stl"
    if len(data) >= STL_HEADER and len(data) == STL_HEADER + STL_TRIANGLE * struct.unpack("<I", data[80:84])[0]:
        return "stl"
    if data.lstrip().startswith(b"{") and b'"asset"' in data[:SNIFF_BYTES]:  # glTF's one required property
        return "gltf"
    line = first_statement(data)
    if line is None:
        return None
    words = line[1]
    if words[0].endswith(b"OFF") and words[0].isalpha():
        return "off"
    if words[0] in OBJ_STATEMENTS:
        return "obj"
    if len(words) in (3, 6) and _numbers(words):
        return "xyz"
    return None


def not_obj(data: bytes) -> str | None:
    """Why ``data``, named .obj but holding no vertex, is no Wavefront OBJ file at all (its first line is not an
    OBJ statement: a text of another kind renamed), or None when it may be one without geometry."""
    line = first_statement(data)
    if line is None or line[1][0] in OBJ_STATEMENTS:
        return None
    number, words = line
    word = words[0].decode("utf-8", "replace")[:30]
    return (f"not a Wavefront OBJ file: line {number} starts with '{word}', not an OBJ statement such as "
            "'v x y z' or 'f 1 2 3'")
