"""Loading, normalising, sampling and exporting shapes.

Everything the rest of the library consumes is a :class:`Shape`: a triangle mesh
or a point cloud (with normals), always in the *input's own frame*.  Models work in
the unit cube; :class:`Normalization` is the exact, reversible map between the two,
so results can be written back where the input was.
"""

from __future__ import annotations

import contextlib
import io
import os
from pathlib import Path

import numpy as np

from .orientation import outward
from .shape import EXPORT_FORMATS, MAX_FACES, MAX_POINTS, Normalization, Shape, ShapeError, too_many

NORMAL_BLOCK = 32_768  # points whose normals are estimated at once (bounds that step's memory)
# Points of a cloud the pipeline reads at most: 4x its largest draw (16,384 support points; a mesh is read as 8,192
# and 16,384 samples).  More only cost memory and time in the steps that read every point (normals, planes, pieces).
CLOUD_POINTS = 65_536
THIN_SEED = 0


# --------------------------------------------------------------------------- loading


def _ext(name: str) -> str:
    return Path(name).suffix.lower().lstrip(".")


def load_shape(source: str | os.PathLike | bytes, filename: str | None = None,
               max_points: int = MAX_POINTS, max_faces: int = MAX_FACES, normals: bool = True,
               texture: bool = False) -> Shape:
    """Read a mesh or point cloud from a path or from bytes.

    Parameters
    ----------
    source : path or bytes
        The file, or its content (then ``filename`` gives the format by extension; without it the content
        does, where it can: :func:`fastmesh.shapes.sniff.sniff_format`).
    filename : str, optional
        Name used for the format when ``source`` is bytes.
    max_points, max_faces : int
        Larger inputs are refused (``ShapeError('too_large')``) before heavy work.
    normals : bool
        Make a point cloud what the pipeline reads (:func:`ready_cloud`): at most :data:`CLOUD_POINTS` of its
        points, each with a unit normal (missing or unusable ones estimated, the costly part of loading a large
        cloud).  False keeps every point and the file's normals as they are (or None); :func:`ready_cloud` does
        the rest later.
    texture : bool
        Read a glTF mesh's base-colour texture and UVs too (``Shape.texture``, for ``bake``).

    Raises
    ------
    ShapeError
        With code ``unsupported_format``, ``unreadable``, ``empty``, ``non_finite``, ``out_of_range``,
        ``degenerate`` or ``too_large``.
    """
    from .pointfiles import load_numpy_points, load_text_points
    from .precheck import check_parse_cost, plain_parse_error
    from .sniff import file_format

    data, name = _read(source, filename)
    if not name and len(data) == 0:
        raise ShapeError("empty", "file is empty")
    ext = file_format(data, name)
    if len(data) == 0:
        raise ShapeError("empty", "file is empty")
    try:
        check_parse_cost(data, ext, max_points, max_faces)  # what reading costs, before a parser spends it
        if ext in ("xyz", "txt"):
            shape = load_text_points(data, max_points)
        elif ext in ("npy", "npz"):
            shape = load_numpy_points(data, ext, max_points)
        else:
            _precheck_mesh(data, ext, max_points, max_faces)
            shape = _load_trimesh(data, ext, texture)
    except ShapeError:
        raise
    except MemoryError:
        raise ShapeError("too_large", "file declares more data than can be loaded") from None
    except Exception as e:  # parsers raise anything from IndexError to struct.error: say what it means
        raise ShapeError("unreadable", plain_parse_error(e, ext, data)) from None
    out = validate_shape(shape, max_points=max_points, max_faces=max_faces, normals=normals)
    out.texture = shape.texture if out.faces is not None else None
    return out


def _read(source: str | os.PathLike | bytes, filename: str | None) -> tuple[bytes, str]:
    """The bytes of ``source`` (a path, or the content itself) and the name that gives its format ("" for
    content without a ``filename``)."""
    if isinstance(source, (bytes, bytearray, memoryview)):
        return bytes(source), filename or ""
    try:
        return Path(source).read_bytes(), filename or str(source)
    except OSError as e:
        raise ShapeError("unreadable", f"cannot read {source}: {e.strerror}") from None


def _precheck_mesh(data: bytes, ext: str, max_points: int, max_faces: int) -> None:
    """Refuse what the parser would choke on, before parsing (see :mod:`fastmesh.shapes.precheck`)."""
    from .gltf_check import check_gltf
    from .ply_check import check_ply
    from .precheck import check_obj, check_off, check_stl

    if ext == "obj":
        check_obj(data, max_points, max_faces)
    elif ext == "stl":
        check_stl(data, max_faces)
    elif ext == "off":
        check_off(data, max_points, max_faces)
    elif ext in ("gltf", "glb"):
        check_gltf(data, ext, max_points, max_faces)
    elif ext == "ply":
        check_ply(data, max_points, max_faces)


def _load_trimesh(data: bytes, ext: str, texture: bool = False) -> Shape:
    """The geometry of a mesh file; with ``texture``, a glTF's base-colour texture too (``texture.texture_of``)."""
    import trimesh

    # Geometry only: an OBJ's materials would make trimesh import an image library for textures that
    # this upload does not carry anyway.
    extra = {"skip_materials": True} if ext == "obj" else {}
    texture = texture and ext in ("glb", "gltf")
    with _images_of_any_size(texture):
        loaded = trimesh.load(io.BytesIO(data), file_type=ext, process=False, **extra)
    found = None
    if isinstance(loaded, trimesh.Scene):
        from .texture import read_texture, texture_of

        for g in loaded.geometry.values():  # dump() copies visuals: a textured one decodes its images
            if isinstance(g, trimesh.Trimesh) and texture:
                read_texture(g)
            elif isinstance(g, trimesh.Trimesh):
                g.visual = trimesh.visual.ColorVisuals()
        geoms = [g for g in loaded.dump() if hasattr(g, "vertices")] if loaded.geometry else []
        meshes = [g for g in geoms if isinstance(g, trimesh.Trimesh) and len(g.faces)]
        if meshes and texture:
            found = texture_of(meshes)
            for g in meshes:  # concatenating textured meshes would pack their images into one
                g.visual = trimesh.visual.ColorVisuals()
        if meshes:
            loaded = trimesh.util.concatenate(meshes)
        elif geoms:
            loaded = trimesh.PointCloud(np.concatenate([np.asarray(g.vertices) for g in geoms]))
        else:
            raise ShapeError("empty", "file holds no geometry")
    if isinstance(loaded, trimesh.Trimesh) and len(loaded.faces) > 0:
        return Shape(vertices=np.asarray(loaded.vertices, dtype=np.float64),
                     faces=np.asarray(loaded.faces, dtype=np.int64), texture=found)
    if hasattr(loaded, "vertices"):
        verts = np.asarray(loaded.vertices, dtype=np.float64)
        normals = None
        vn = getattr(loaded, "metadata", {}).get("_ply_raw", None)
        if vn is not None:  # PLY point cloud with nx, ny, nz properties
            props = vn.get("vertex", {}).get("data", None)
            # binary PLY gives a structured array, ASCII PLY a dict of columns
            names = props.dtype.names if hasattr(props, "dtype") else props if isinstance(props, dict) else None
            if names and all(k in names for k in ("nx", "ny", "nz")):
                normals = np.stack([np.asarray(props[k]).reshape(-1) for k in ("nx", "ny", "nz")], axis=1)
                normals = normals.astype(np.float64)
        return Shape(vertices=verts.reshape(-1, 3), normals=normals)
    raise ShapeError("unreadable", f"no mesh or points found in .{ext} file")


@contextlib.contextmanager
def _images_of_any_size(on: bool):
    """With ``on``, images of any size open (their headers only): PIL refuses a large one at its opening, which the
    glTF reader takes silently for no texture; ``texture.read_texture`` refuses it by its size, saying so."""
    if not on:
        yield
        return
    from PIL import Image

    bomb = Image.MAX_IMAGE_PIXELS
    Image.MAX_IMAGE_PIXELS = None
    try:
        yield
    finally:
        Image.MAX_IMAGE_PIXELS = bomb


def validate_shape(shape: Shape, max_points: int = MAX_POINTS, max_faces: int = MAX_FACES,
                   normals: bool = True) -> Shape:
    """Check a shape for the failures every consumer would trip over.

    Geometry checks (face areas, collinearity) run in the unit cube, so coordinates anywhere in
    float64's range give the same answers.  ``normals``: thin a point cloud and complete its normals
    (:func:`ready_cloud`); False keeps what the file gave (all its points, its normals or None).
    """
    v = np.asarray(shape.vertices, dtype=np.float64)
    if v.ndim != 2 or v.shape[1] != 3 or len(v) == 0:
        raise ShapeError("empty", "shape has no vertices")
    if len(v) > max_points:
        raise too_many(len(v), max_points)
    if not np.isfinite(v).all():
        raise ShapeError("non_finite", "coordinates contain NaN or infinity")
    unit = Normalization.fit(v).apply(v)  # raises on zero or unusable extent
    faces = shape.faces
    if faces is not None:
        faces = np.asarray(faces, dtype=np.int64)
        if len(faces) > max_faces:
            raise too_many(len(faces), max_faces, "faces")
        if faces.size and (faces.min() < 0 or faces.max() >= len(v)):
            raise ShapeError("unreadable", f"a face refers to a vertex the file does not have (it has {len(v)} "
                                           "vertices)")
        area = _face_areas(unit, faces)
        faces = faces[area > 0]
        if len(faces) == 0:
            raise ShapeError("degenerate", "every face has zero area")
        return Shape(vertices=v, faces=faces)
    if len(v) < 4:
        raise ShapeError("degenerate", f"a point cloud needs at least 4 points, got {len(v)}")
    centred = unit - unit.mean(0)
    sv = np.linalg.svd(centred[:: max(1, len(v) // 20000)], compute_uv=False)
    if sv[1] <= 1e-9 * sv[0]:
        raise ShapeError("degenerate", "points are collinear; no surface can be built")
    given = shape.normals
    if given is not None:
        given = np.asarray(given, dtype=np.float64)
        if given.shape != v.shape:
            given = None
    out = Shape(vertices=v, normals=given)
    return ready_cloud(out) if normals else out


def thinned(shape: Shape, n: int = CLOUD_POINTS, seed: int = THIN_SEED) -> Shape:
    """A point cloud of at most ``n`` of the shape's points (a seeded uniform draw, kept in the file's order) with
    their normals; a mesh, or a cloud of ``n`` points or fewer, as it is.

    Parameters
    ----------
    shape : Shape
        (N, 3) vertices, (N, 3) normals or None.
    n : int
        Points kept at most (:data:`CLOUD_POINTS`).
    seed : int
        Seed of the draw: equal inputs give equal clouds, whichever interface reads them.
    """
    if shape.faces is not None or len(shape.vertices) <= n:
        return shape
    keep = np.sort(np.random.default_rng(seed).choice(len(shape.vertices), size=n, replace=False))
    normals = None if shape.normals is None else np.asarray(shape.normals)[keep]
    return Shape(vertices=np.asarray(shape.vertices)[keep], normals=normals)


def ready_cloud(shape: Shape) -> Shape:
    """A point cloud as the pipeline reads it: :func:`thinned`, then :func:`with_normals` (estimated on the points
    kept); a mesh as it is.  ``load_shape`` and the worker both call it, so a cloud gives one mesh through either."""
    return with_normals(thinned(shape))


def with_normals(shape: Shape) -> Shape:
    """The point cloud with a unit normal at every point: the given ones where finite and non-zero,
    estimated ones (:func:`estimate_normals`) elsewhere, all of them turned outward where the points enclose a
    volume (``orientation.outward``) when none was given.  A mesh is returned as it is.

    All-zero or NaN normal columns are what some exporters write for "no normals"; taken as given
    they would all point one way and mislead the models.
    """
    if shape.faces is not None:
        return shape
    given = shape.normals
    if given is not None:
        given = np.asarray(given, dtype=np.float64)
        with np.errstate(over="ignore", invalid="ignore"):
            length = np.linalg.norm(given, axis=1)
        usable = np.isfinite(length) & (length > 1e-12)
    if given is None or not usable.any():  # signs of our own guess: outward wherever the points tell
        return Shape(vertices=shape.vertices, normals=outward(shape.vertices, estimate_normals(shape.vertices)))
    if usable.all():
        return Shape(vertices=shape.vertices, normals=given / length[:, None])
    out = estimate_normals(shape.vertices)
    out[usable] = given[usable] / length[usable, None]
    return Shape(vertices=shape.vertices, normals=out)


def _face_areas(v: np.ndarray, faces: np.ndarray) -> np.ndarray:
    tri = v[faces]
    return 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)


def _unit(x: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(x, axis=-1, keepdims=True)
    return np.where(n > 0, x / np.maximum(n, 1e-12), np.array([0.0, 0.0, 1.0]))


def estimate_normals(points: np.ndarray, k: int = 12) -> np.ndarray:
    """PCA normals from ``k`` nearest neighbours, flipped to face away from the centroid.

    Computed in the unit cube: squared distances of coordinates far from 1 would overflow (or
    underflow) the kd-tree.  Outward orientation by centroid is a heuristic (wrong inside
    concavities), but the models only need a consistent-ish signal; the authors' data had true normals.

    Returns
    -------
    (N, 3) float64 unit normals.
    """
    from scipy.spatial import cKDTree

    points = Normalization.fit(points).apply(points)
    n = len(points)
    k = min(k, n)
    tree = cKDTree(points)
    normals = np.empty_like(points)
    # In blocks: the neighbourhoods of all points at once take ~0.9 KB a point (430 MB for 500,000).
    for lo in range(0, n, NORMAL_BLOCK):
        _, idx = tree.query(points[lo:lo + NORMAL_BLOCK], k=k)
        nb = points[idx] - points[idx].mean(1, keepdims=True)  # (block, k, 3)
        _, vecs = np.linalg.eigh(np.einsum("nki,nkj->nij", nb, nb))
        normals[lo:lo + NORMAL_BLOCK] = vecs[:, :, 0]  # smallest eigenvalue
    outward = points - points.mean(0)
    flip = (normals * outward).sum(1) < 0
    normals[flip] *= -1
    return _unit(normals)


# --------------------------------------------------------------------------- sampling


def sample_surface(shape: Shape, n: int, seed: int | None = 0,
                   vertices: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Area-weighted surface samples with normals.

    Parameters
    ----------
    shape : Shape
        A mesh (sampled on its triangles) or a point cloud (resampled to ``n``).
    n : int
        Number of samples.
    seed : int or None
        Seed of the generator; equal seeds give equal samples.
    vertices : (N, 3) array, optional
        Positions to use instead of ``shape.vertices`` (e.g. normalised ones).

    Returns
    -------
    points : (n, 3) float32
    normals : (n, 3) float32, unit length
    """
    rng = np.random.default_rng(seed)
    v = shape.vertices if vertices is None else np.asarray(vertices, dtype=np.float64)
    if shape.faces is None:
        idx = rng.choice(len(v), size=n, replace=len(v) < n)
        return v[idx].astype(np.float32), shape.normals[idx].astype(np.float32)
    return sample_triangles(v, shape.faces, n, rng)


def input_surface(shape: Shape, vertices: np.ndarray, n: int, seed: int | None) -> np.ndarray:
    """(<= n, 3) samples of the input surface at ``vertices`` (the shape's, in another frame) for the
    face support check: a point cloud of at most ``n`` points gives all of them (resampling would
    duplicate points and hide their spacing)."""
    if shape.faces is None and len(vertices) <= n:
        return np.asarray(vertices)
    return sample_surface(shape, n, seed=seed, vertices=vertices)[0]


def sample_triangles(v: np.ndarray, faces: np.ndarray, n: int,
                     rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Uniform samples on triangles ``v[faces]``; returns (n, 3) points and face normals."""
    tri = v[faces]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area = np.linalg.norm(cross, axis=1)
    total = area.sum()
    if total <= 0:
        raise ShapeError("degenerate", "mesh has zero surface area")
    fi = rng.choice(len(faces), size=n, p=area / total)
    r1, r2 = rng.random(n), rng.random(n)
    s = np.sqrt(r1)
    a, b, c = 1 - s, s * (1 - r2), s * r2
    pts = a[:, None] * tri[fi, 0] + b[:, None] * tri[fi, 1] + c[:, None] * tri[fi, 2]
    normals = cross[fi] / np.maximum(area[fi, None], 1e-20)
    return pts.astype(np.float32), normals.astype(np.float32)


# --------------------------------------------------------------------------- export


def export_mesh(vertices: np.ndarray, faces: np.ndarray, fmt: str) -> bytes:
    """Serialise a triangle mesh to ``glb``, ``obj`` or ``ply`` bytes."""
    import trimesh

    fmt = fmt.lower()
    if fmt not in EXPORT_FORMATS:
        raise ShapeError("unsupported_format", f"cannot export '{fmt}'; use one of {', '.join(EXPORT_FORMATS)}")
    mesh = trimesh.Trimesh(vertices=np.asarray(vertices, dtype=np.float64),
                           faces=np.asarray(faces, dtype=np.int64).reshape(-1, 3), process=False)
    out = mesh.export(file_type=fmt)
    return out.encode("utf-8") if isinstance(out, str) else bytes(out)


def write_mesh(path: str | os.PathLike, vertices: np.ndarray, faces: np.ndarray, fmt: str | None = None) -> None:
    fmt = fmt or _ext(str(path))
    Path(path).write_bytes(export_mesh(vertices, faces, fmt))
