"""Point-cloud files: text (``.xyz``, ``.txt``) and NumPy (``.npy``, ``.npz``) into a
:class:`~fastmesh.shapes.shape.Shape`.

Both read what they are given with bounded memory: text rows are streamed into one flat array,
array headers are checked against the limits before any data is read.
"""

from __future__ import annotations

import array
import io

import numpy as np

from .precheck import parse_budget
from .shape import Shape, ShapeError, too_many

MAX_TEXT_LINE = 1024  # characters in one line of a text point file (six numbers take ~150)


def load_text_points(data: bytes, max_points: int) -> Shape:
    """x y z [nx ny nz] per line; '#' starts a comment line; commas count as spaces.

    Lines end at \\n, \\r\\n or \\r and nowhere else (str.splitlines would also split at form feeds,
    U+2028 and more, which a line count could not anticipate).  Rows are read one at a time into a
    flat array, so memory stays a small multiple of the upload whatever its lines hold.
    """
    # Lines that are not comments ('#' first) or empty bound the points from above: refuse early.
    text_lines = data.count(b"\n") + data.count(b"\r") - data.count(b"\r\n") + (not data.endswith((b"\n", b"\r")))
    lines = text_lines - data.count(b"\n#") - data.startswith(b"#") - data.count(b"\n\n") - data.count(b"\n\r\n")
    if lines > max_points:
        raise ShapeError("too_large", f"{lines} lines exceed the limit of {max_points} points")
    most, _ = parse_budget("xyz", max_points, 0)  # comments and blank lines are read too
    if text_lines > most:
        raise ShapeError("too_large", f"{text_lines} lines exceed the limit of {most} lines of a text point file "
                                      f"(its {max_points} points, comments and blank lines)")
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as e:
        raise ShapeError("unreadable", f"text point file is not UTF-8 text (byte {e.start} is not)") from None
    values = array.array("d")
    width = rows = 0
    for number, line in enumerate(io.StringIO(text, newline=None), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        if len(line) > MAX_TEXT_LINE:
            raise ShapeError("unreadable", f"line {number} is {len(line)} characters long; each line holds 3 (x y z) "
                                           "or 6 (x y z nx ny nz) numbers")
        parts = line.replace(",", " ").split()
        if width == 0:
            width = len(parts)
        if len(parts) not in (3, 6) or len(parts) != width:
            raise ShapeError("unreadable", f"line {number} holds {len(parts)} values; each line must hold 3 (x y z) "
                                           f"or 6 (x y z nx ny nz) numbers, the same on every line")
        try:
            values.extend(float(p) for p in parts)
        except ValueError:
            bad = next(p for p in parts if not _is_float(p))
            raise ShapeError("unreadable", f"line {number}: '{bad[:30]}' is not a number") from None
        rows += 1
        if rows > max_points:
            raise too_many(rows, max_points)
    if rows == 0:
        raise ShapeError("empty", "no points in file")
    return _points_from_array(np.frombuffer(values, dtype=np.float64).reshape(rows, width))


def _is_float(s: str) -> bool:
    try:
        float(s)
        return True
    except ValueError:
        return False


def _npy_rows(f, max_points: int) -> None:
    """Read an .npy header from ``f`` and refuse more than ``max_points`` rows before any data is read.

    An .npz member is compressed: a 1 MB upload can declare gigabytes of zeros (a zip bomb).
    """
    try:
        version = np.lib.format.read_magic(f)
    except ValueError:
        raise ShapeError("unreadable", "not a NumPy .npy array (its signature is missing or damaged)") from None
    try:
        if version == (1, 0):
            shape, _, dtype = np.lib.format.read_array_header_1_0(f)
        else:
            shape, _, dtype = np.lib.format.read_array_header_2_0(f)
    except ValueError:
        raise ShapeError("unreadable", "the .npy array header is damaged (it does not say the array's shape "
                                       "and type)") from None
    rows = shape[0] if shape else 1
    if rows > max_points:
        raise too_many(rows, max_points)
    if int(np.prod(shape, dtype=np.float64)) * dtype.itemsize > max_points * 6 * 8:  # wider than N x 6 float64
        raise ShapeError("too_large", f"array of shape {shape} is larger than {max_points} points")


def load_numpy_points(data: bytes, ext: str, max_points: int) -> Shape:
    if ext == "npy":
        _npy_rows(io.BytesIO(data), max_points)
    # allow_pickle=False: an .npy upload must never execute code.
    obj = np.load(io.BytesIO(data), allow_pickle=False)
    if ext == "npz":
        if not hasattr(obj, "keys"):
            raise ShapeError("unreadable", "not an .npz archive (a zip of .npy arrays); name a single array .npy")
        keys = list(obj.keys())
        if not keys:
            raise ShapeError("empty", "npz archive holds no arrays")
        key = next((k for k in ("points", "pointcloud", "xyz", "arr_0") if k in keys), keys[0])
        for k in (key, "normals") if "normals" in keys else (key,):
            with obj.zip.open(f"{k}.npy") as member:
                _npy_rows(member, max_points)
        arr = obj[key]
        if "normals" in keys and arr.ndim == 2 and arr.shape[1] == 3:
            normals = obj["normals"]
            if normals.shape != arr.shape:
                raise ShapeError("unreadable", f"npz 'normals' has shape {normals.shape}; it must match the points' "
                                               f"{arr.shape}")
            arr = np.concatenate([arr, normals], axis=1)
    else:
        arr = obj
    if arr.dtype.kind not in "fiu" or arr.ndim != 2 or arr.shape[1] not in (3, 6):
        raise ShapeError("unreadable", f"expected an N x 3 or N x 6 numeric array, got {arr.dtype} {arr.shape}")
    return _points_from_array(arr.astype(np.float64))


def _points_from_array(arr: np.ndarray) -> Shape:
    if len(arr) == 0:
        raise ShapeError("empty", "no points in file")
    normals = arr[:, 3:6] if arr.shape[1] == 6 else None
    return Shape(vertices=arr[:, :3].copy(), normals=normals)
