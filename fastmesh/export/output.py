"""The result as it is written: quads (``topology=quad``), a UV layout (``uv``), the input's texture baked onto it
(``bake``) and its placement (``origin``, ``height``, ``up``), with the files of each format.

GLB holds triangles (glTF has no quads) and is always Y-up; OBJ and PLY hold the quads and are turned for
``up=z``; OBJ and GLB hold the UVs, GLB the baked texture.
"""

from __future__ import annotations

import io
from dataclasses import dataclass, field

import numpy as np

from . import layout as uvs
from .layout import UVLayout, uv_layout
from .meshfiles import glb_bytes, obj_bytes, ply_bytes
from .placement import Placement, placement, turn_up
from .quads import EdgeEvidence, pair_triangles, quad_corners, quad_share

FORMATS = ("glb", "obj", "ply")


@dataclass
class MeshOut:
    """A result ready to write.

    Attributes
    ----------
    vertices : (V, 3) float64, placed, Y-up
    faces : (F, 3) int64, triangles
    pairs : (Q, 4) int64, triangles merged into quads (``quads.pair_triangles`` rows)
    layout : UVLayout or None
    texture : (S, S, 4) uint8 RGBA or None, the base colour on ``layout``
    up : str, the up axis of the OBJ and PLY files
    """

    vertices: np.ndarray
    faces: np.ndarray
    pairs: np.ndarray = field(default_factory=lambda: np.zeros((0, 4), np.int64))
    layout: UVLayout | None = None
    texture: np.ndarray | None = None
    up: str = "y"

    def polygons(self) -> tuple[list[np.ndarray], list[np.ndarray] | None]:
        """``([quads (Q, 4), triangles (T, 3)], the same shapes of UV rows or None)``: the pairs as quads, the
        other triangles as they are.  A pair whose diagonal is a UV seam stays two triangles (a polygon has
        one UV per corner)."""
        pairs = self.pairs
        lay = self.layout
        if lay is not None and len(pairs):
            f, g, i, j = (pairs[:, k] for k in range(4))
            same = ((lay.faces[g, j] == lay.faces[f, (i + 1) % 3]) & (lay.faces[g, (j + 1) % 3] == lay.faces[f, i]))
            pairs = pairs[same]
        merged = np.zeros(len(self.faces), dtype=bool)
        merged[pairs[:, 0]] = merged[pairs[:, 1]] = True
        single = np.flatnonzero(~merged)
        polys = [quad_corners(self.faces, pairs), self.faces[single]]
        if lay is None:
            return polys, None
        return polys, [quad_corners(lay.faces, pairs), lay.faces[single]]

    def export(self, fmt: str) -> bytes:
        """The result as ``glb``, ``obj`` or ``ply`` bytes."""
        from ..shapes.io import export_mesh
        from ..shapes.shape import ShapeError

        fmt = fmt.lower()
        if fmt not in FORMATS:
            raise ShapeError("unsupported_format", f"cannot export '{fmt}'; use one of {', '.join(FORMATS)}")
        lay = self.layout
        if fmt == "glb":
            if lay is None:
                return export_mesh(self.vertices, self.faces, "glb")
            return glb_bytes(self.vertices[lay.vertex], lay.faces, lay.uv, self.texture)
        v = turn_up(self.vertices, self.up)
        if not len(self.pairs) and (lay is None or fmt == "ply"):  # triangles only: trimesh's writers, as ever
            return export_mesh(v, self.faces, fmt)
        polys, poly_uv = self.polygons()
        if fmt == "ply":
            return ply_bytes(v, polys)
        return obj_bytes(v, polys, None if lay is None else lay.uv, poly_uv)

    def counts(self) -> dict:
        """Quads and triangles as OBJ and PLY write them, and the quads' share of those polygons."""
        polys, _ = self.polygons()
        quads, tris = len(polys[0]), len(polys[1])
        return {"quads": quads, "quad_share": quad_share(quads, tris)}

    def to_npz(self) -> bytes:
        """Everything needed to write any format again (:meth:`from_npz`); ``vertices`` and ``faces`` as the
        plain mesh npz the previews read."""
        arrays = {"vertices": self.vertices, "faces": self.faces, "pairs": self.pairs, "up": np.array(self.up)}
        if self.layout is not None:
            arrays.update(uv=self.layout.uv, uv_faces=self.layout.faces, uv_vertex=self.layout.vertex,
                          uv_size=np.int64(self.layout.size))
        if self.texture is not None:
            arrays["texture"] = self.texture
        buf = io.BytesIO()
        np.savez_compressed(buf, **arrays)  # a baked texture is mostly flat colour: it shrinks several times
        return buf.getvalue()

    @classmethod
    def from_npz(cls, data: bytes) -> MeshOut:
        with np.load(io.BytesIO(data), allow_pickle=False) as z:
            layout = None
            if "uv" in z:
                layout = UVLayout(uv=z["uv"], faces=z["uv_faces"], vertex=z["uv_vertex"], size=int(z["uv_size"]))
            return cls(vertices=z["vertices"], faces=z["faces"].astype(np.int64),
                       pairs=z["pairs"].astype(np.int64) if "pairs" in z else np.zeros((0, 4), np.int64),
                       layout=layout, texture=z["texture"] if "texture" in z else None,
                       up=str(z["up"]) if "up" in z else "y")


def finish(vertices: np.ndarray, faces: np.ndarray, params, source=None, evidence: EdgeEvidence | None = None
           ) -> tuple[MeshOut, Placement, list[str]]:
    """The result ``vertices`` (V, 3, the input's frame) and ``faces`` (F, 3) made ready to write as ``params``
    (:class:`fastmesh.params.GenerateParams`) ask.

    ``source`` is the input :class:`fastmesh.shapes.shape.Shape`, whose texture ``bake`` reads; ``evidence`` the face
    model's edges, whose flat 4-cliques become quads first (:func:`fastmesh.export.quads.pair_triangles`).  Returns the
    :class:`MeshOut`, its placement and notes for people on what a format leaves out.

    Raises
    ------
    ValueError
        ``height`` of a result that is flat along Y.
    """
    from .bake import bake

    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    where = placement(vertices, params.origin, params.height, params.up)  # refuses before the slower steps
    notes = []
    pairs = (pair_triangles(vertices, faces, evidence=evidence) if params.topology == "quad"
             else np.zeros((0, 4), np.int64))
    if params.topology == "quad":
        notes.append("GLB holds triangles only (glTF has no quads): the quads are in the OBJ and PLY files")
    layout = texture = None
    if params.uv:
        layout = uv_layout(vertices, faces, size=uvs.TEXTURE_SIZE)  # read now: a test may make it smaller
        notes.append("the UV layout is in the GLB (TEXCOORD_0) and OBJ (vt) files; PLY holds none")
    if params.bake:
        found = getattr(source, "texture", None)
        if found is None or source.faces is None:
            notes.append("bake: the input has no base-colour texture that could be read (a textured GLB or glTF), "
                         "so none was baked")
        else:
            texture = bake(vertices, faces, layout, source.vertices, source.faces, found)
            notes.append("the baked texture is in the GLB file (OBJ holds the UVs, without a material)")
    if params.up == "z":
        notes.append("up=z turns the OBJ and PLY files; GLB stays Y-up, as glTF requires")
    out = MeshOut(vertices=where.apply(vertices), faces=faces, pairs=pairs, layout=layout, texture=texture,
                  up=params.up)
    return out, where, notes
