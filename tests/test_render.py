"""Pixel checks of the preview renderer on scenes whose answer is known."""

from __future__ import annotations

import itertools
import struct
import zlib

import numpy as np
import pytest
import trimesh

from fastmesh.preview.render import (
    DEFAULT_CONFIG,
    RenderConfig,
    fit_camera,
    render_mesh,
    render_points,
    render_shape,
    to_png,
)
from fastmesh.shapes.shape import Shape, ShapeError

SIZE = 96
BG = np.rint(np.asarray(DEFAULT_CONFIG.background) * 255).astype(np.uint8)
# The camera's axes in world coordinates (independent of the shape): right, up, towards viewer.
RIGHT, UP, TOWARDS = fit_camera(np.eye(3), SIZE).rotation


def view_quad(corners_xyz) -> np.ndarray:
    """(4, 3) corners given in camera axes (x right, y up, z towards viewer) -> world positions."""
    c = np.asarray(corners_xyz, dtype=np.float64)
    return c[:, :1] * RIGHT + c[:, 1:2] * UP + c[:, 2:3] * TOWARDS


def quad_faces(offset: int) -> np.ndarray:
    return np.array([[0, 1, 2], [0, 2, 3]]) + offset


def scene(*quads) -> tuple[np.ndarray, np.ndarray]:
    v = np.concatenate(quads)
    f = np.concatenate([quad_faces(4 * i) for i in range(len(quads))])
    return v, f


def flat_color(v, f) -> np.ndarray:
    """The single flat colour a planar quad renders with (its middle pixel)."""
    img = render_mesh(v, f, SIZE)
    return img[SIZE // 2, SIZE // 2].astype(int)


# Two squares facing the viewer, the small one in front; the small one is tilted so it shades differently.
BACK = view_quad([[-1, -1, -1], [1, -1, -1], [1, 1, -1], [-1, 1, -1]])
FRONT = view_quad([[-0.4, -0.4, 1.0], [0.4, -0.4, 0.2], [0.4, 0.4, 0.2], [-0.4, 0.4, 1.0]])


def test_quad_in_front_hides_the_one_behind_whatever_the_face_order():
    front_color, back_color = flat_color(FRONT, quad_faces(0)), flat_color(BACK, quad_faces(0))
    assert np.abs(front_color - back_color).max() > 20  # the scene can tell them apart
    v, f = scene(BACK, FRONT)
    for perm in itertools.permutations(range(4)):
        img = render_mesh(v, f[list(perm)], SIZE).astype(int)
        # middle: only the front quad; near a corner: only the back quad
        assert np.abs(img[SIZE // 2, SIZE // 2] - front_color).max() <= 1, perm
        assert np.abs(img[8, 8] - back_color).max() <= 1, perm


def test_intersecting_quads_resolve_per_pixel():
    # A is nearer in the upper half, B in the lower: painter's sorting of whole faces cannot draw this.
    a = view_quad([[-1, -1, -0.5], [1, -1, -0.5], [1, 1, 0.5], [-1, 1, 0.5]])
    b = view_quad([[-1, -1, 0.5], [1, -1, 0.5], [1, 1, -0.5], [-1, 1, -0.5]])
    ca, cb = flat_color(a, quad_faces(0)), flat_color(b, quad_faces(0))
    assert np.abs(ca - cb).max() > 20
    v, f = scene(a, b)
    for perm in itertools.permutations(range(4)):
        img = render_mesh(v, f[list(perm)], SIZE).astype(int)
        for col in (SIZE // 4, SIZE // 2, 3 * SIZE // 4):
            assert np.abs(img[int(SIZE * 0.25), col] - ca).max() <= 1, perm
            assert np.abs(img[int(SIZE * 0.75), col] - cb).max() <= 1, perm


def test_face_order_does_not_change_the_image():
    m = trimesh.creation.icosphere(subdivisions=2)
    faces = np.asarray(m.faces)
    a = render_mesh(m.vertices, faces, SIZE)
    rng = np.random.default_rng(0)
    perm = rng.permutation(len(faces))
    flipped = faces[perm][:, ::-1]  # also reverse every winding: lighting is two-sided
    b = render_mesh(m.vertices, flipped, SIZE)
    differ = (np.abs(a.astype(int) - b.astype(int)).max(2) > 2).mean()
    assert differ < 0.002  # only exact depth ties on shared edges may go the other way


def test_wireframe_darkens_edges_only():
    v, f = BACK, quad_faces(0)
    plain = render_mesh(v, f, SIZE).astype(int)
    wire = render_mesh(v, f, SIZE, wireframe=True).astype(int)
    lum_plain, lum_wire = plain.sum(2), wire.sum(2)
    darker = lum_wire < lum_plain - 30
    assert darker.sum() > SIZE  # the outline and the diagonal
    assert lum_wire.min() < lum_plain.min() - 100  # really dark lines
    # Pixels well inside each triangle are untouched; pixels on the diagonal are dark.
    x, y, _ = fit_camera(v, SIZE).project(v)
    for tri in f:
        cx, cy = x[tri].mean(), y[tri].mean()
        assert np.abs(wire[int(cy), int(cx)] - plain[int(cy), int(cx)]).max() <= 1
    mx, my = (x[0] + x[2]) / 2, (y[0] + y[2]) / 2  # on the shared diagonal 0-2
    assert darker[int(my) - 1:int(my) + 2, int(mx) - 1:int(mx) + 2].any()
    assert (plain == wire)[~darker].mean() > 0.9


def test_hidden_edges_are_not_drawn():
    # The back quad's diagonal 0-2 runs behind the front quad, whose own diagonal is the other
    # one (its corners start one step later): the back diagonal must not show through.
    v, f = scene(BACK, np.roll(FRONT, 1, axis=0))
    x, y, _ = fit_camera(v, SIZE).project(v)
    wire = render_mesh(v, f, SIZE, wireframe=True).astype(int)
    plain = render_mesh(v, f, SIZE).astype(int)
    t = np.linspace(0, 1, 400)
    px, py = x[0] + (x[2] - x[0]) * t, y[0] + (y[2] - y[0]) * t
    # On the back diagonal, inside the front quad, 4..9 px from its centre (clear of its edges).
    r = np.hypot(px - SIZE / 2, py - SIZE / 2)
    probe = {(int(a), int(b)) for a, b, d in zip(px, py, r, strict=True) if 4 < d < 9}
    assert len(probe) >= 6
    for cx, cy in probe:
        assert np.abs(wire[cy, cx] - plain[cy, cx]).max() <= 1
    # ...while outside the front quad the same diagonal is drawn.
    far = [(int(a), int(b)) for a, b, d in zip(px, py, r, strict=True) if 34 < d < 42]
    assert all(wire[cy, cx].sum() < plain[cy, cx].sum() - 60 for cx, cy in far)


def test_background_is_empty_and_image_is_framed():
    img = render_mesh(BACK, quad_faces(0), SIZE)
    for corner in (img[0, 0], img[0, -1], img[-1, 0], img[-1, -1]):
        assert (corner == BG).all()
    rgba = render_mesh(BACK, quad_faces(0), SIZE, alpha=True)
    assert rgba.shape == (SIZE, SIZE, 4) and rgba[0, 0, 3] == 0 and rgba[SIZE // 2, SIZE // 2, 3] == 255


@pytest.mark.parametrize("scale,offset", [(1.0, 0.0), (1e-3, 0.0), (250.0, 1e5)])
@pytest.mark.parametrize("shape", ["sphere", "long_box"])
def test_object_fills_the_image_without_being_clipped(shape, scale, offset):
    if shape == "sphere":
        m = trimesh.creation.icosphere(subdivisions=2)
    else:
        m = trimesh.creation.box(extents=[4.0, 0.3, 0.5])
    v = np.asarray(m.vertices) * scale + offset
    img = render_mesh(v, m.faces, SIZE)
    obj = (img != BG).any(2)
    border = np.concatenate([obj[0], obj[-1], obj[:, 0], obj[:, -1]])
    assert not border.any()  # nothing touches the edge: not clipped
    rows, cols = np.flatnonzero(obj.any(1)), np.flatnonzero(obj.any(0))
    span = max(rows[-1] - rows[0], cols[-1] - cols[0]) + 1
    assert span >= 0.85 * SIZE  # fills the image
    centre = ((rows[0] + rows[-1]) / 2, (cols[0] + cols[-1]) / 2)
    assert np.allclose(centre, (SIZE - 1) / 2, atol=2)


def test_unreferenced_vertices_do_not_shrink_the_framing():
    v = np.concatenate([BACK, [[100.0, 100.0, 100.0]]])
    img = render_mesh(v, quad_faces(0), SIZE)
    assert (img != BG).any(2).mean() > 0.4


def test_overlay_points_are_depth_tested():
    v, f = BACK, quad_faces(0)
    pts = view_quad([[0.5, 0.5, 0.3], [-0.5, -0.5, -1.5], [0.0, 0.0, -1.0]])  # in front / behind / on it
    cam = fit_camera(np.concatenate([v, pts]), SIZE)
    x, y, _ = cam.project(pts)
    img = render_mesh(v, f, SIZE, points=pts).astype(int)
    orange = (img[:, :, 0] - img[:, :, 2]) > 60

    def near(i):
        return orange[int(y[i]) - 1:int(y[i]) + 2, int(x[i]) - 1:int(x[i]) + 2].any()

    assert near(0)  # in front of the quad: visible
    assert not near(1)  # behind the quad: hidden
    assert near(2)  # on the surface: visible thanks to the depth bias


def test_point_cloud_near_points_hide_far_ones():
    rng = np.random.default_rng(1)
    uv = rng.uniform(-1, 1, size=(4000, 2))
    near = view_quad(np.c_[uv * 0.5, np.full(len(uv), 0.5)])
    far = view_quad(np.c_[uv, np.full(len(uv), -0.5)])
    normals = np.tile(TOWARDS, (8000, 1))
    pts = np.concatenate([far, near])
    a = render_points(pts, size=SIZE).astype(int)
    b = render_points(pts[::-1], size=SIZE).astype(int)
    assert (np.abs(a - b).max(2) > 2).mean() < 0.002
    middle, edge = a[SIZE // 2 - 3:SIZE // 2 + 3, SIZE // 2 - 3:SIZE // 2 + 3].mean(), a[12, 12].mean()
    assert middle > edge + 10  # depth cue: the near layer (lighter) covers the middle
    shaded = render_points(pts, normals=normals, size=SIZE)
    assert (shaded != BG).any(2).mean() > 0.3
    assert render_shape(Shape(vertices=pts, normals=normals), size=SIZE).shape == (SIZE, SIZE, 3)


def test_large_point_clouds_are_subsampled_deterministically():
    pts = np.random.default_rng(2).normal(size=(5000, 3))
    cfg = RenderConfig(max_points=1000)
    a, b = render_points(pts, size=SIZE, config=cfg), render_points(pts, size=SIZE, config=cfg)
    assert (a == b).all() and (a != BG).any()


@pytest.mark.parametrize("make", [
    lambda: render_mesh(BACK, np.zeros((0, 3), dtype=int)),
    lambda: render_mesh(np.zeros((0, 3)), quad_faces(0)),
    lambda: render_mesh(np.where(np.arange(12).reshape(4, 3) == 5, np.nan, BACK), quad_faces(0)),
    lambda: render_mesh(BACK, quad_faces(0) + 2),  # index 4, 5 out of range
    lambda: render_mesh(BACK[:, :2], quad_faces(0)),
    lambda: render_mesh(BACK, [[0, 1]]),
    lambda: render_mesh(BACK, [[0.5, 1, 2]]),
    lambda: render_mesh(np.ones((4, 3)), quad_faces(0)),  # zero extent
    lambda: render_mesh(BACK, quad_faces(0), points=[[np.inf, 0, 0]]),
    lambda: render_mesh(BACK, quad_faces(0), size=0),
    lambda: render_points(np.zeros((0, 3))),
    lambda: render_points([[0, 0, 0], [1, 1, np.nan]]),
    lambda: render_points(np.eye(3), normals=np.eye(2)),
    lambda: to_png(np.zeros((4, 4, 3), dtype=np.float32)),
    lambda: to_png(np.zeros((4, 4, 2), dtype=np.uint8)),
])
def test_bad_input_is_a_clear_value_error(make):
    with pytest.raises(ValueError) as e:
        make()
    assert len(str(e.value)) > 10


def test_bad_geometry_errors_carry_a_code():
    with pytest.raises(ShapeError) as e:
        render_mesh(np.full((3, 3), np.nan), [[0, 1, 2]])
    assert e.value.code == "non_finite"
    with pytest.raises(ShapeError) as e:
        render_mesh(BACK, np.zeros((0, 3), dtype=int))
    assert e.value.code == "empty"


# --------------------------------------------------------------------------- PNG


def decode_png(data: bytes) -> np.ndarray:
    """Independent minimal PNG reader (8-bit, non-interlaced; all five filter types)."""
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    pos, idat, header = 8, b"", None
    while pos < len(data):
        (n,) = struct.unpack(">I", data[pos:pos + 4])
        kind, body = data[pos + 4:pos + 8], data[pos + 8:pos + 8 + n]
        (crc,) = struct.unpack(">I", data[pos + 8 + n:pos + 12 + n])
        assert crc == zlib.crc32(kind + body) & 0xFFFFFFFF, kind
        if kind == b"IHDR":
            header = struct.unpack(">IIBBBBB", body)
        elif kind == b"IDAT":
            idat += body
        pos += 12 + n
    w, h, depth, ctype, _, _, interlace = header
    assert depth == 8 and interlace == 0
    c = {0: 1, 2: 3, 6: 4}[ctype]
    raw = zlib.decompress(idat)
    stride = w * c
    out = np.zeros((h, stride), dtype=np.int64)
    prev = np.zeros(stride, dtype=np.int64)
    for r in range(h):
        ftype = raw[r * (stride + 1)]
        line = np.frombuffer(raw, np.uint8, stride, r * (stride + 1) + 1).astype(np.int64)
        cur = np.zeros(stride, dtype=np.int64)
        for i in range(stride):
            a = cur[i - c] if i >= c else 0
            b, cc = prev[i], (prev[i - c] if i >= c else 0)
            if ftype == 0:
                pred = 0
            elif ftype == 1:
                pred = a
            elif ftype == 2:
                pred = b
            elif ftype == 3:
                pred = (a + b) // 2
            else:
                p = a + b - cc
                pa, pb, pc = abs(p - a), abs(p - b), abs(p - cc)
                pred = a if pa <= pb and pa <= pc else (b if pb <= pc else cc)
            cur[i] = (line[i] + pred) % 256
        out[r], prev = cur, cur
    return out.reshape(h, w, c).astype(np.uint8)


@pytest.mark.parametrize("alpha", [False, True])
def test_png_round_trip_of_a_render(alpha):
    m = trimesh.creation.icosphere(subdivisions=1)
    img = render_mesh(m.vertices, m.faces, 48, wireframe=True, alpha=alpha)
    assert (decode_png(to_png(img)) == img).all()


@pytest.mark.parametrize("shape", [(5, 7), (5, 7, 1), (6, 3, 3), (3, 6, 4)])
def test_png_round_trip_of_noise(shape):
    img = np.random.default_rng(3).integers(0, 256, size=shape, dtype=np.uint8)
    back = decode_png(to_png(img))
    assert (back == img.reshape(back.shape)).all()


def test_face_batches_give_the_same_image():
    m = trimesh.creation.icosphere(subdivisions=2)
    whole = render_mesh(m.vertices, m.faces, SIZE, wireframe=True)
    batched = render_mesh(m.vertices, m.faces, SIZE, wireframe=True, config=RenderConfig(face_batch=37))
    assert (whole == batched).all()
