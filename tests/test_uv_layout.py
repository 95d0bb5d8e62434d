"""uv=true and bake=true: xatlas UV layouts (fastmesh.export.layout) in the GLB (TEXCOORD_0) and OBJ (vt) files, and a
textured glTF input's base colour baked onto them (fastmesh.export.bake)."""

from __future__ import annotations

import io
import json
import struct

import numpy as np
import pytest
import trimesh
from PIL import Image
from test_quads import read_obj
from trimesh.visual import TextureVisuals
from trimesh.visual.material import PBRMaterial

from fastmesh.export.bake import sample
from fastmesh.export.layout import overlap_share, rasterize, uv_layout
from fastmesh.export.output import MeshOut
from fastmesh.faces.meshops import closest_on_triangles
from fastmesh.params import GenerateParams
from fastmesh.pipeline import Pipeline
from fastmesh.shapes.io import load_shape
from fastmesh.shapes.shape import Shape
from fastmesh.shapes.texture import SurfaceTexture

# The six sides of the textured box, in the order textured_box_glb makes them: -X, +X, -Y, +Y, -Z, +Z.
COLOURS = np.array([[230, 20, 20], [20, 230, 20], [20, 20, 230], [230, 230, 20], [20, 230, 230], [230, 20, 230]])
SIDES = [(axis, sign) for axis in range(3) for sign in (-1, 1)]


@pytest.fixture(scope="module")
def pipe():
    return Pipeline.random("tiny", seed=0)


def textured_box_glb(center=(0.0, 0.0, 0.0), size=1.0) -> bytes:
    """A cube (24 vertices: each side its own 4) whose sides map to six cells of one 96 x 64 texture, each cell
    one of :data:`COLOURS`, as a GLB with a base-colour texture."""
    image = np.zeros((64, 96, 4), np.uint8)
    image[..., 3] = 255
    verts, faces, uv = [], [], []
    for k, (axis, sign) in enumerate(SIDES):
        a, b = [i for i in range(3) if i != axis]
        corners = []
        for ca, cb in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
            p = np.zeros(3)
            p[axis], p[a], p[b] = sign, ca, cb
            corners.append(p * size / 2 + center)
        normal = np.cross(corners[1] - corners[0], corners[2] - corners[0])
        outward = np.dot(normal, np.eye(3)[axis] * sign) > 0
        base = len(verts)
        verts += corners
        faces += [[base, base + 1, base + 2], [base, base + 2, base + 3]] if outward else \
            [[base, base + 2, base + 1], [base, base + 3, base + 2]]
        row, col = divmod(k, 3)
        image[row * 32:(row + 1) * 32, col * 32:(col + 1) * 32, :3] = COLOURS[k]
        u0, u1 = (col * 32 + 4) / 96, (col * 32 + 28) / 96  # inside the cell: bilinear sampling stays in it
        v0, v1 = 1 - (row * 32 + 28) / 64, 1 - (row * 32 + 4) / 64
        uv += [[u0, v0], [u1, v0], [u1, v1], [u0, v1]]
    material = PBRMaterial(baseColorTexture=Image.fromarray(image, "RGBA"))
    mesh = trimesh.Trimesh(np.array(verts), np.array(faces), visual=TextureVisuals(uv=np.array(uv), material=material),
                           process=False)
    return mesh.export(file_type="glb")


def glb_json(data: bytes) -> dict:
    """The JSON chunk of a GLB."""
    assert data[:4] == b"glTF"
    length = struct.unpack("<I", data[12:16])[0]
    return json.loads(data[20:20 + length])


def side_of(normal: np.ndarray) -> int:
    axis = int(np.argmax(np.abs(normal)))
    return SIDES.index((axis, int(np.sign(normal[axis]))))


def test_layout_of_a_curved_mesh_fills_the_unit_square_without_overlap():
    sphere = trimesh.creation.icosphere(3)
    lay = uv_layout(sphere.vertices * 1e4 + 5e5, sphere.faces)  # far off and large: the unit cube inside
    assert np.array_equal(lay.vertex[lay.faces], sphere.faces)  # row f of the layout is triangle f
    assert lay.uv.min() >= 0 and lay.uv.max() <= 1 and len(lay.uv) > len(sphere.vertices)  # split along seams
    assert overlap_share(lay.uv, lay.faces) < 1e-3
    covered = len(np.unique(rasterize(lay.uv, lay.faces, 256)[1])) / 256**2
    assert covered > 0.4, covered  # packed, not a few specks in a corner
    # Area-weighted stretch is small: each triangle keeps its share of the surface in UV space.
    tri3, tri2 = sphere.vertices[sphere.faces], lay.uv[lay.faces]
    a3 = np.linalg.norm(np.cross(tri3[:, 1] - tri3[:, 0], tri3[:, 2] - tri3[:, 0]), axis=1)
    e1, e2 = tri2[:, 1] - tri2[:, 0], tri2[:, 2] - tri2[:, 0]
    a2 = np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
    ratio = (a2 / a2.sum()) / (a3 / a3.sum())
    assert np.median(np.abs(np.log(ratio))) < 0.3


def test_overlap_share_sees_an_overlap():
    uv = np.array([[0.1, 0.1], [0.9, 0.1], [0.1, 0.9], [0.9, 0.9]])
    assert overlap_share(uv, np.array([[0, 1, 2], [1, 3, 2]])) == 0  # two triangles sharing an edge
    assert overlap_share(uv, np.array([[0, 1, 2], [0, 1, 3]])) > 0.3  # two over the same texels


def test_uv_layout_in_glb_and_obj(pipe):
    box = trimesh.creation.box(extents=(1, 2, 3))
    res = pipe.generate(Shape(vertices=np.asarray(box.vertices), faces=np.asarray(box.faces)),
                        GenerateParams(uv=True, topology="quad"))
    glb = res.export("glb")
    prim = glb_json(glb)["meshes"][0]["primitives"][0]
    assert "TEXCOORD_0" in prim["attributes"]
    mesh = trimesh.load(io.BytesIO(glb), file_type="glb", force="mesh", process=False)
    uv = mesh.visual.uv
    assert uv.shape == (len(mesh.vertices), 2) and uv.min() >= 0 and uv.max() <= 1
    assert overlap_share(uv, mesh.faces) < 1e-3
    assert np.allclose(mesh.area, 22.0) and len(mesh.faces) == 12
    # OBJ: vt rows and every corner's v/vt; the six quads keep their UVs (no diagonal is a seam on a box).
    v, faces, vt, face_uv = read_obj(res.export("obj"))
    assert len(vt) and vt.min() >= 0 and vt.max() <= 1
    assert [len(f) for f in face_uv] == [len(f) for f in faces] == [4] * 6
    tris = np.array([[f[0], f[i], f[i + 1]] for f in face_uv for i in (1, 2)])
    assert overlap_share(vt, tris) < 1e-3
    # A corner's vt in the OBJ is the GLB's UV at the same position.
    glb_uv = {tuple(np.round(p, 6)) + tuple(np.round(t, 6)) for p, t in zip(mesh.vertices, uv, strict=True)}
    for f, fu in zip(faces, face_uv, strict=True):
        for i, j in zip(f, fu, strict=True):
            assert tuple(np.round(v[i], 6)) + tuple(np.round(vt[j], 6)) in glb_uv
    assert any("PLY holds none" in n for n in res.info["notes"])
    assert "TEXCOORD_0" not in glb_json(pipe.generate(Shape(vertices=np.asarray(box.vertices),
                                                            faces=np.asarray(box.faces))).export("glb"))["meshes"][0][
        "primitives"][0]["attributes"]


def test_a_seam_on_a_quads_diagonal_keeps_it_two_triangles():
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
    f = np.array([[0, 1, 2], [0, 2, 3]])
    pairs = np.array([[0, 1, 2, 0]])  # the diagonal 2 -> 0 of face 0 is 0 -> 2 of face 1
    lay = uv_layout(v, f)
    one = MeshOut(vertices=v, faces=f, pairs=pairs, layout=lay)
    assert one.counts()["quads"] == 1
    lay.uv = np.concatenate([lay.uv, lay.uv[lay.faces[1]] * 0.5])  # face 1 on UV vertices of its own
    lay.faces = np.array([lay.faces[0], [len(lay.uv) - 3, len(lay.uv) - 2, len(lay.uv) - 1]])
    split = MeshOut(vertices=v, faces=f, pairs=pairs, layout=lay)
    assert split.counts() == {"quads": 0, "quad_share": 0.0}
    assert [len(x) for x in read_obj(split.export("obj"))[1]] == [3, 3]


def test_load_shape_reads_the_texture_only_when_asked():
    data = textured_box_glb()
    assert load_shape(data, "box.glb").texture is None
    tex = load_shape(data, "box.glb", texture=True).texture
    assert tex.uv.shape == (24, 2) and tex.image_of.tolist() == [0] * 24 and len(tex.images) == 1
    assert tex.images[0].shape == (64, 96, 4) and np.allclose(tex.factors, 1)
    assert load_shape(trimesh.creation.box().export(file_type="glb"), "b.glb", texture=True).texture is None
    again = SurfaceTexture.from_arrays(tex.to_arrays())
    assert np.allclose(again.uv, tex.uv, atol=1e-6) and np.array_equal(again.images[0], tex.images[0])


def test_bake_moves_each_sides_colour_onto_the_new_layout(pipe):
    shape = load_shape(textured_box_glb(center=(3.0, 1.0, -2.0), size=2.0), "box.glb", texture=True)
    res = pipe.generate(shape, GenerateParams(uv=True, bake=True, topology="quad", origin="bottom", height=1.0))
    assert res.info["result_from"] == "input" and len(res.faces) == 12  # the welded box: one UV layout anew
    mesh = trimesh.load(io.BytesIO(res.export("glb")), file_type="glb", force="mesh", process=False)
    assert "baseColorTexture" in glb_json(res.export("glb"))["materials"][0]["pbrMetallicRoughness"]
    baked = np.asarray(mesh.visual.material.baseColorTexture.convert("RGBA"))
    assert baked.shape == (1024, 1024, 4)
    # Each triangle's colour, read at points inside it on the new layout, is its side's.
    bary = np.array([[1, 1, 1], [4, 1, 1], [1, 4, 1], [1, 1, 4]]) / np.array([[3], [6], [6], [6]])
    for f, normal in zip(mesh.faces, mesh.face_normals, strict=True):
        got = sample(baked, bary @ mesh.visual.uv[f])[:, :3]
        assert np.abs(got - COLOURS[side_of(normal)]).max() <= 2, (got, side_of(normal))
    # Placed after baking: the bottom centre at the origin, 1 m tall.
    assert np.allclose(mesh.bounds, [[-0.5, 0, -0.5], [0.5, 1, 0.5]])


def test_bake_without_a_texture_says_so_and_needs_uv(pipe):
    box = trimesh.creation.box()
    res = pipe.generate(Shape(vertices=np.asarray(box.vertices), faces=np.asarray(box.faces)),
                        GenerateParams(uv=True, bake=True))
    assert any("no base-colour texture" in n for n in res.info["notes"])
    assert "baseColorTexture" not in json.dumps(glb_json(res.export("glb")).get("materials"))
    with pytest.raises(ValueError, match="bake needs uv=true"):
        pipe.generate(Shape(vertices=np.asarray(box.vertices), faces=np.asarray(box.faces)), GenerateParams(bake=True))


def test_closest_point_on_triangles():
    tri = np.array([[[0, 0, 0], [1, 0, 0], [0, 1, 0]]] * 3, float)
    p = np.array([[0.2, 0.2, 5.0], [2.0, -1.0, 0.0], [-1.0, 0.5, 1.0]])
    bary = closest_on_triangles(p, tri)
    near = np.einsum("nk,nkd->nd", bary, tri)
    assert np.allclose(near, [[0.2, 0.2, 0], [1, 0, 0], [0, 0.5, 0]])
    assert np.allclose(near, trimesh.triangles.closest_point(tri, p))


def test_two_textures_each_bake_onto_their_own_triangles():
    """A scene of two textured cubes with different images: each triangle takes its own cube's image."""
    from fastmesh.export.bake import bake
    from fastmesh.faces.meshops import weld

    a = trimesh.load(io.BytesIO(textured_box_glb(center=(-2.0, 0, 0))), file_type="glb", force="mesh")
    b = trimesh.load(io.BytesIO(textured_box_glb(center=(2.0, 0, 0))), file_type="glb", force="mesh")
    flipped = np.asarray(b.visual.material.baseColorTexture.convert("RGBA"))[:, :, [2, 1, 0, 3]]  # red <-> blue
    b.visual.material = PBRMaterial(baseColorTexture=Image.fromarray(np.ascontiguousarray(flipped), "RGBA"))
    scene = trimesh.Scene([a, b])
    shape = load_shape(scene.export(file_type="glb"), "two.glb", texture=True)
    tex = shape.texture
    assert len(tex.images) == 2 and set(tex.image_of.tolist()) == {0, 1}
    v, f = weld(shape.vertices, shape.faces)
    lay = uv_layout(v, f, size=256)
    baked = bake(v, f, lay, shape.vertices, shape.faces, tex)
    for face, uv_rows in zip(f, lay.faces, strict=True):
        tri = v[face]
        n = np.cross(tri[1] - tri[0], tri[2] - tri[0])
        want = COLOURS[side_of(n)][[2, 1, 0]] if tri[:, 0].mean() > 0 else COLOURS[side_of(n)]
        got = sample(baked, lay.uv[uv_rows].mean(axis=0, keepdims=True))[0, :3]
        assert np.abs(got - want).max() <= 2, (got, want)


def test_an_image_that_does_not_decode_is_no_texture(pipe):
    data = bytearray(textured_box_glb())
    start = data.index(b"IDAT") + 8
    data[start:start + 40] = b"\xff" * 40  # the compressed pixels: the header still reads
    shape = load_shape(bytes(data), "box.glb", texture=True)
    assert shape.texture is None and len(shape.faces) == 12
    res = pipe.generate(shape, GenerateParams(uv=True, bake=True))
    assert any("no base-colour texture that could be read" in n for n in res.info["notes"])
