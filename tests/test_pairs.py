"""Pair evidence of the face model: grid distances against brute force, symmetry, meaning, zero start."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh
from test_models_face import _shape, _t, tiny_config

from fastmesh.models.face import FaceModel
from fastmesh.models.pairs import STRAY_CLIP, distance_grid, pair_context, pair_features, point_spacing

torch.set_num_threads(1)


def _sphere(n_points: int = 1024, seed: int = 0):
    pts, fi = trimesh.sample.sample_surface(trimesh.creation.icosphere(3, radius=0.45), n_points, seed=seed)
    nrm = pts / np.linalg.norm(pts, axis=1, keepdims=True)
    return torch.tensor(pts, dtype=torch.float32)[None], torch.tensor(nrm, dtype=torch.float32)[None]


def test_distance_grid_nodes_equal_brute_force():
    pts, _ = _sphere(300)
    grid = distance_grid(pts, 9)[0, 0]
    ax = np.linspace(-0.5, 0.5, 9)
    rng = np.random.default_rng(0)
    for ix, iy, iz in rng.integers(0, 9, (20, 3)):
        node = torch.tensor([[ax[ix], ax[iy], ax[iz]]], dtype=torch.float32)
        want = torch.cdist(node, pts[0]).min()
        torch.testing.assert_close(grid[iz, iy, ix], want)


def test_pair_features_match_brute_force_segments():
    """The slow twin: every segment sample measured against every point (tolerance: the grid's cell)."""
    pts, nrm = _sphere()
    rng = np.random.default_rng(1)
    xyz = torch.tensor(rng.uniform(-0.45, 0.45, (1, 12, 3)), dtype=torch.float32)
    ctx = pair_context(xyz, pts, nrm, grid=64, samples=6)
    got = pair_features(ctx, 0, 12)[0]  # (12, 12, 5)
    spacing = point_spacing(pts)[0]
    a, b = xyz[0][:, None], xyz[0][None]
    t = (torch.arange(6) + 0.5) / 6
    samples = a[..., None, :] + t[:, None] * (b - a)[..., None, :]  # (12, 12, 6, 3)
    d = torch.cdist(samples.reshape(-1, 3), pts[0]).min(dim=1).values.view(12, 12, 6) / spacing
    cell = (1.0 / 63) * 3 ** 0.5 / spacing  # a trilinear read is off by at most the cell's diagonal
    torch.testing.assert_close(got[..., 0], d.max(-1).values.clamp(max=STRAY_CLIP), atol=float(cell), rtol=0)
    torch.testing.assert_close(got[..., 1], d.mean(-1).clamp(max=STRAY_CLIP), atol=float(cell), rtol=0)
    length = (b - a).norm(dim=-1)
    off = ~torch.eye(12, dtype=torch.bool)
    torch.testing.assert_close(got[..., 2][off], torch.log(length / spacing)[off])
    near = torch.cdist(xyz[0], pts[0]).argmin(dim=1)
    n = nrm[0][near]
    e = (b - a) / length.clamp(min=1e-9)[..., None]
    ci, cj = (n[:, None] * e).sum(-1).abs(), (n[None] * e).sum(-1).abs()
    torch.testing.assert_close(got[..., 3][off], torch.maximum(ci, cj)[off])
    torch.testing.assert_close(got[..., 4][off], torch.minimum(ci, cj)[off])


def test_pair_features_are_exactly_symmetric_and_chunked_equals_whole():
    pts, nrm = _sphere(512)
    xyz = torch.tensor(np.random.default_rng(2).uniform(-0.5, 0.5, (1, 17, 3)), dtype=torch.float32)
    for samples in (5, 6):
        ctx = pair_context(xyz, pts, nrm, grid=32, samples=samples)
        whole = pair_features(ctx, 0, 17)[0]
        assert torch.equal(whole, whole.transpose(0, 1))
        parts = torch.cat([pair_features(ctx, s, min(s + 4, 17)) for s in range(0, 17, 4)], dim=1)[0]
        assert torch.equal(parts, whole)


def test_pair_features_tell_surface_edges_from_chords():
    """On a sphere, a short segment between neighbouring surface points stays on the surface and lies
    across the normals; a chord through the middle strays far and runs along them."""
    pts, nrm = _sphere(2048)
    u = torch.tensor([[0.0, 0.0, 0.45], [0.05, 0.0, 0.447], [0.0, 0.0, -0.45]])
    f = pair_features(pair_context(u[None], pts, nrm, grid=48, samples=6), 0, 3)[0]
    edge, chord = f[0, 1], f[0, 2]
    assert edge[0] < 1.5 and chord[0] == STRAY_CLIP
    assert edge[2] < chord[2]
    assert edge[3] < 0.3 and chord[4] > 0.9


def test_zero_pair_weights_continue_a_model_without_them():
    torch.manual_seed(0)
    plain = FaceModel(tiny_config()).eval()
    with_pairs = FaceModel(tiny_config(pair_evidence=True)).eval()
    missing, unexpected = with_pairs.load_state_dict(plain.state_dict(), strict=False)
    assert missing == ["pair_fc.weight"] and not unexpected
    q, pts, nrm = _shape(16)
    with torch.no_grad():
        a = plain(*_t(q, pts, nrm))
        b = with_pairs(*_t(q, pts, nrm))
        torch.testing.assert_close(a, b)
        with_pairs.pair_fc.weight.normal_()
        assert not torch.allclose(with_pairs(*_t(q, pts, nrm)), a, atol=1e-3)  # the features do enter


def test_pair_model_needs_points():
    m = FaceModel(tiny_config(pair_evidence=True)).eval()
    q, pts, nrm = _shape(8)
    prefix = m.backbone.condition(*_t(q, pts, nrm)[1:])
    with pytest.raises(ValueError, match="points and normals"):
        m(torch.from_numpy(q)[None], prefix=prefix)
