"""Writers of polygon meshes that trimesh's exporters cannot write: OBJ with quads and per-corner UVs
(``vt``), binary PLY with quads, and GLB with a UV layout (``TEXCOORD_0``) and a base-colour texture.

Polygons are given as a list of (P, k) int arrays, one per corner count k (3 or 4), 0-based.
"""

from __future__ import annotations

import io

import numpy as np

HEADER = "# FastMesh"


def _rows(fmt: str, values: np.ndarray) -> str:
    """``values`` (N, k) written one row a line with the %-format ``fmt`` of one row."""
    if len(values) == 0:
        return ""
    buf = io.StringIO()
    np.savetxt(buf, values, fmt=fmt)
    return buf.getvalue()


def obj_bytes(vertices: np.ndarray, polygons: list[np.ndarray], uv: np.ndarray | None = None,
              polygon_uv: list[np.ndarray] | None = None) -> bytes:
    """A Wavefront OBJ of ``vertices`` (V, 3) and ``polygons``; with ``uv`` (W, 2), ``vt`` lines and faces
    ``v/vt`` whose UV rows ``polygon_uv`` gives (shaped as ``polygons``).

    Vertices are written with 9 significant digits (float32 exactly; trimesh's OBJ writer keeps 8 decimals).
    """
    v = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    parts = [f"{HEADER}: {len(v)} vertices, {sum(len(p) for p in polygons)} faces\n", _rows("v %.9g %.9g %.9g", v)]
    if uv is not None:
        parts.append(_rows("vt %.9g %.9g", np.asarray(uv, dtype=np.float64).reshape(-1, 2)))
    for k, poly in enumerate(polygons):
        poly = np.asarray(poly, dtype=np.int64)
        if len(poly) == 0:
            continue
        n = poly.shape[1]
        if uv is None:
            parts.append(_rows("f" + " %d" * n, poly + 1))
        else:
            both = np.stack([poly + 1, np.asarray(polygon_uv[k], dtype=np.int64) + 1], axis=2).reshape(len(poly), -1)
            parts.append(_rows("f" + " %d/%d" * n, both))
    return "".join(parts).encode()


def ply_bytes(vertices: np.ndarray, polygons: list[np.ndarray]) -> bytes:
    """A binary little-endian PLY of ``vertices`` (V, 3, written float32 as trimesh's exporter does) and
    ``polygons`` (a ``uchar`` count and ``int`` indices each)."""
    v = np.asarray(vertices, dtype="<f4").reshape(-1, 3)
    n_faces = sum(len(p) for p in polygons)
    head = (f"ply\nformat binary_little_endian 1.0\ncomment {HEADER[2:]}\nelement vertex {len(v)}\n"
            "property float x\nproperty float y\nproperty float z\n"
            f"element face {n_faces}\nproperty list uchar int vertex_indices\nend_header\n").encode()
    blocks = [head, v.tobytes()]
    for poly in polygons:
        poly = np.asarray(poly, dtype=np.int64)
        if len(poly) == 0:
            continue
        rows = np.zeros(len(poly), dtype=[("n", "u1"), ("v", "<i4", (poly.shape[1],))])
        rows["n"], rows["v"] = poly.shape[1], poly
        blocks.append(rows.tobytes())
    return b"".join(blocks)


def glb_bytes(vertices: np.ndarray, faces: np.ndarray, uv: np.ndarray | None = None,
              texture: np.ndarray | None = None) -> bytes:
    """A GLB of the triangles ``faces`` (F, 3) at ``vertices`` (V, 3); with ``uv`` (V, 2, OBJ's convention: v
    up) as ``TEXCOORD_0`` and an unlit-neutral PBR material (metallic 0, roughness 1) whose base colour is
    ``texture`` (S, S, 4) uint8 RGBA when given."""
    import trimesh
    from trimesh.visual import TextureVisuals
    from trimesh.visual.material import PBRMaterial

    visual = None
    if uv is not None:
        image = None
        if texture is not None:
            from PIL import Image

            image = Image.fromarray(np.asarray(texture, dtype=np.uint8), "RGBA")
        visual = TextureVisuals(uv=np.asarray(uv, dtype=np.float64),
                                material=PBRMaterial(baseColorTexture=image, metallicFactor=0.0,
                                                     roughnessFactor=1.0))
    mesh = trimesh.Trimesh(vertices=np.asarray(vertices, dtype=np.float64),
                           faces=np.asarray(faces, dtype=np.int64).reshape(-1, 3), visual=visual, process=False)
    return bytes(mesh.export(file_type="glb"))
