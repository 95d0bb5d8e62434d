"""Round trips of the vertex, vanilla and BPT tokenizers (property tests) and the vertex grammar."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from fastmesh.tokenizer import bpt, dequantize, grid, quantize, quantize_mesh, sort_key, vanilla, vertex
from fastmesh.tokenizer.grid import LEVELS

SETTINGS = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])

cell = st.tuples(*[st.integers(0, LEVELS - 1)] * 3)
cells = st.lists(cell, min_size=1, max_size=80)


@st.composite
def meshes(draw, max_vertices: int = 40, max_faces: int = 80):
    """Random quantised meshes: cells (repeats allowed) and faces (degenerate ones allowed)."""
    q = np.array(draw(st.lists(cell, min_size=3, max_size=max_vertices)))
    n = len(q)
    f = np.array(draw(st.lists(st.tuples(*[st.integers(0, n - 1)] * 3), min_size=1, max_size=max_faces)))
    return q, f.reshape(-1, 3)


def _grid_mesh(k: int, rng: np.random.Generator):
    """A jittered k x k height field: a manifold, consistently oriented mesh with fans."""
    x, y = np.meshgrid(np.arange(k), np.arange(k), indexing="ij")
    z = rng.integers(0, 20, size=x.shape)
    q = np.stack([x * 5, y * 5, z], axis=-1).reshape(-1, 3)
    idx = np.arange(k * k).reshape(k, k)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    f = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return q, f


# --------------------------------------------------------------------------- vertex tokenizer


@SETTINGS
@given(cells)
def test_vertex_round_trip(c):
    q = np.array(c)
    tok = vertex.encode(q)
    out = vertex.decode(tok)
    expect = vertex.cells_from_keys(np.unique(sort_key(q)))
    assert np.array_equal(out, expect)
    assert len(tok) == vertex.num_tokens(q)
    assert tok.min() >= 0 and tok.max() < vertex.VOCAB_SIZE


@SETTINGS
@given(cells)
def test_vertex_grammar_accepts_every_encoding(c):
    tok = vertex.encode(np.array(c))
    assert tok[0] == vertex.BOS and tok[-1] == vertex.EOS
    block, offset = -1, -1
    for prev, t in zip(tok[:-1], tok[1:], strict=True):
        ranges = vertex.allowed_ranges(int(prev), block, offset)
        assert any(lo <= t < hi for lo, hi in ranges), (prev, t, ranges)
        if vertex.BLOCK0 <= t < vertex.OFFSET0:
            block, offset = int(t) - vertex.BLOCK0, -1
        elif t >= vertex.OFFSET0:
            offset = int(t) - vertex.OFFSET0


def test_vertex_grammar_rejects_bad_moves():
    tok = vertex.encode(np.array([[0, 0, 0], [0, 0, 1], [20, 0, 0]]))
    b0 = int(tok[1]) - vertex.BLOCK0
    o1 = int(tok[3]) - vertex.OFFSET0
    ranges = vertex.allowed_ranges(int(tok[3]), b0, o1)
    assert not any(lo <= vertex.OFFSET0 + o1 < hi for lo, hi in ranges)  # no repeated offset
    assert not any(lo <= vertex.BLOCK0 + b0 < hi for lo, hi in ranges)  # no repeated block
    assert vertex.allowed_ranges(vertex.BOS, -1, -1) == [(vertex.BLOCK0, vertex.OFFSET0)]


def test_vertex_decode_strict_errors():
    with pytest.raises(ValueError):
        vertex.decode([vertex.BOS, vertex.OFFSET0 + 1, vertex.EOS])
    with pytest.raises(ValueError):
        vertex.decode([vertex.BOS, vertex.BLOCK0, vertex.OFFSET0 + 5, vertex.OFFSET0 + 5, vertex.EOS])
    out = vertex.decode([vertex.BOS, vertex.BLOCK0, vertex.OFFSET0 + 5, vertex.OFFSET0 + 5, vertex.EOS], strict=False)
    assert len(out) == 1
    with pytest.raises(ValueError):
        vertex.encode(np.array([[0, 0, LEVELS]]))


def test_quantize_round_trip_within_half_cell():
    rng = np.random.default_rng(0)
    v = rng.uniform(-0.5, 0.5, size=(1000, 3))
    q = quantize(v)
    assert q.min() >= 0 and q.max() <= LEVELS - 1
    assert np.abs(dequantize(q) - v).max() <= 0.5 * grid.CELL + 1e-12
    assert np.array_equal(quantize(dequantize(q)), q)


# --------------------------------------------------------------------------- the grid


def test_grid_bit_layout():
    """Cell (65, 66, 127) is block (4, 4, 7), offset (1, 2, 15): ids x major, key = block * 4096 + offset."""
    block, offset = grid.split_cells(np.array([65, 66, 127]))
    assert (block, offset) == (4 * 64 + 4 * 8 + 7, 1 * 256 + 2 * 16 + 15)
    assert sort_key(np.array([[65, 66, 127]])).tolist() == [block * 4096 + offset]
    assert grid.flat_index(np.array([65, 66, 127])) == (65 * 128 + 66) * 128 + 127
    assert quantize(np.array([-0.5, 0.5, 0.5 - 1e-9])).tolist() == [0, 127, 127]  # the faces close the cube


@SETTINGS
@given(c=cells)
def test_grid_split_join_and_flat_are_inverses(c):
    q = np.array(c)
    assert np.array_equal(grid.join_cells(*grid.split_cells(q)), q)
    assert np.array_equal(grid.cells_from_keys(sort_key(q)), q)
    assert np.array_equal(grid.unflat_index(grid.flat_index(q)), q)
    block, offset = grid.split_cells(q)
    assert np.array_equal(grid.split_key(sort_key(q))[0], block) and np.array_equal(grid.block_coords(block), q >> 4)
    assert np.array_equal(grid.offset_coords(offset), q % 16)
    for res in (2, 8, 64):  # the coarse grids of the evidence
        assert np.array_equal(grid.unflat_index(grid.flat_index(q % res, res), res), q % res)


def test_grid_numpy_and_torch_agree():
    torch = pytest.importorskip("torch")
    rng = np.random.default_rng(0)
    v = np.concatenate([rng.uniform(-0.6, 0.6, (500, 3)), [[-0.5, 0.5, 0.0], [0.5 - 1e-7, -0.5 + 1e-7, 1.0]]])
    q = quantize(v)
    assert np.array_equal(quantize(torch.from_numpy(v)).numpy(), q)  # float64 in: the same floors
    assert quantize(torch.from_numpy(v)).dtype == torch.int64
    qt = torch.from_numpy(q)
    centres = dequantize(qt)
    assert centres.dtype == torch.float32 and np.allclose(centres.numpy(), dequantize(q), atol=1e-7)
    assert np.array_equal(dequantize(qt.double()).numpy(), dequantize(q))
    assert np.array_equal(grid.grid_coords(torch.from_numpy(v)).numpy(), grid.grid_coords(v))
    block, offset = grid.split_cells(q)
    tb, to = grid.split_cells(qt)
    assert np.array_equal(tb.numpy(), block) and np.array_equal(to.numpy(), offset)
    assert np.array_equal(grid.join_cells(tb, to).numpy(), grid.join_cells(block, offset))
    assert np.array_equal(grid.sort_key(qt).numpy(), sort_key(q))
    assert np.array_equal(grid.cells_from_keys(torch.from_numpy(sort_key(q))).numpy(), q)
    assert np.array_equal(grid.flat_index(qt).numpy(), grid.flat_index(q))
    assert np.array_equal(grid.unflat_index(grid.flat_index(qt)).numpy(), q)
    assert grid.unflat_index(torch.arange(5, dtype=torch.int32)).dtype == torch.int64


# --------------------------------------------------------------------------- vanilla


@SETTINGS
@given(meshes())
def test_vanilla_round_trip(mesh):
    q, f = mesh
    cq, cf = vanilla.canonical_mesh(q, f)
    tok = vanilla.encode(q, f)
    dq, df = vanilla.decode(tok)
    assert np.array_equal(dq, cq) and np.array_equal(df, cf)
    assert len(tok) == vanilla.num_tokens(q, f) == 9 * len(cf) + 2
    assert tok.max(initial=0) < vanilla.VOCAB_SIZE


def test_vanilla_truncated_keeps_complete_faces():
    q, f = _grid_mesh(4, np.random.default_rng(1))
    tok = vanilla.encode(q, f)
    dq, df = vanilla.decode(tok[:1 + 9 * 3 + 4])  # three faces and part of a fourth, no EOS
    assert len(df) == 3


def test_canonical_mesh_preserves_winding_and_geometry():
    q = np.array([[5, 5, 5], [0, 0, 0], [9, 0, 0], [5, 5, 5]])
    f = np.array([[0, 1, 2], [1, 2, 3], [2, 1, 0]])  # faces 0 and 1 equal after the merge; face 2 reversed
    cq, cf = vanilla.canonical_mesh(q, f)
    assert len(cq) == 3 and len(cf) == 1
    assert np.array_equal(cq[cf[0]], q[[1, 2, 0]])  # rotation of (0, 1, 2): same winding


# --------------------------------------------------------------------------- BPT


@SETTINGS
@given(meshes())
def test_bpt_round_trip_exact(mesh):
    q, f = mesh
    cq, cf = vanilla.canonical_mesh(q, f)
    tok = bpt.encode(q, f)
    dq, df = bpt.decode(tok)
    assert np.array_equal(dq, cq) and np.array_equal(df, cf)  # same faces, same winding
    assert len(tok) == bpt.num_tokens(q, f)
    assert tok.max(initial=0) < bpt.VOCAB_SIZE


@SETTINGS
@given(meshes(), st.booleans())
def test_bpt_undirected_round_trip_face_set(mesh, explicit):
    q, f = mesh
    cq, cf = vanilla.canonical_mesh(q, f)
    dq, df = bpt.decode(bpt.encode(q, f, oriented=False, first_block_explicit=explicit))
    assert np.array_equal(dq, cq)
    assert np.array_equal(np.unique(np.sort(df, 1), axis=0), np.unique(np.sort(cf, 1), axis=0))


@pytest.mark.parametrize("oriented", [True, False])
def test_bpt_on_oriented_manifold(oriented):
    q, f = _grid_mesh(12, np.random.default_rng(2))
    q, f = vanilla.canonical_mesh(q, f)
    tok = bpt.encode(q, f, oriented=oriented)
    dq, df = bpt.decode(tok)
    assert np.array_equal(dq, q) and np.array_equal(df, f)  # consistent mesh: winding exact both ways
    # Fans share their centre: far fewer tokens than 9 per face, and fewer than 3 vertices per face.
    assert len(tok) < 0.35 * vanilla.num_tokens(q, f)
    n_patch = int((tok >= bpt.PATCH0).sum())
    assert n_patch < len(f) / 2


def test_bpt_sphere_ratio():
    s = trimesh.creation.icosphere(subdivisions=3)
    q, f, _ = quantize_mesh(s.vertices / 2.01, s.faces)
    nb, nv = bpt.num_tokens(q, f), vanilla.num_tokens(q, f)
    assert 0.15 < nb / nv < 0.35
    assert bpt.num_tokens(q, f, first_block_explicit=True) >= nb
    assert vertex.num_tokens(q) < nb


def test_bpt_decode_errors():
    with pytest.raises(ValueError):
        bpt.decode([bpt.BOS, bpt.OFFSET0, bpt.OFFSET0 + 1, bpt.EOS])  # no patch token
    with pytest.raises(ValueError):
        bpt.decode([bpt.BOS, bpt.PATCH0, bpt.OFFSET0, bpt.OFFSET0 + 1, bpt.EOS])  # centre + one vertex
    with pytest.raises(ValueError):
        bpt.decode([bpt.BOS, bpt.VOCAB_SIZE, bpt.EOS])
    q, f = bpt.decode([bpt.BOS, bpt.PATCH0, bpt.OFFSET0, bpt.OFFSET0 + 1, bpt.EOS], strict=False)
    assert len(f) == 0
    q, f = bpt.decode([bpt.BOS, bpt.PATCH0, bpt.OFFSET0, bpt.OFFSET0 + 1, bpt.OFFSET0 + 2, bpt.EOS])
    assert len(q) == 3 and len(f) == 1


def test_empty_mesh():
    q = np.zeros((0, 3), dtype=np.int64)
    f = np.zeros((0, 3), dtype=np.int64)
    assert vanilla.num_tokens(q, f) == 2 and bpt.num_tokens(q, f) == 2
    assert len(bpt.decode(bpt.encode(q, f))[1]) == 0
