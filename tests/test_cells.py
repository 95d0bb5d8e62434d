"""Cell evidence (models.cells): candidates, features against a per-cell loop, invariances, selection, and the
decoder's reading of the log-odds."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

from fastmesh.models.cells import (
    FLOOR,
    LEVELS,
    PLANE_FIT_RANK,
    SHIFTS,
    CellNet,
    CellNetConfig,
    candidate_cells,
    cell_features,
    dense_grid,
    flat_index,
    n_features,
    select_cells,
    snap_to_cells,
)
from fastmesh.models.encoder import EncoderConfig
from fastmesh.models.evidence import GAIN, PointEvidence
from fastmesh.models.generate import SamplingConfig, generate, generate_uncached
from fastmesh.models.vertex import VertexConfig, VertexDecoder
from fastmesh.tokenizer import vertex as vt
from fastmesh.tokenizer.grid import join_cells

torch.set_num_threads(1)


def _box_points(n: int = 2048, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    box = trimesh.creation.box((0.5, 0.4, 0.3))  # room to move by 16 cells inside the unit cube
    pts, fi = trimesh.sample.sample_surface(box, n, seed=seed)
    return torch.tensor(pts, dtype=torch.float32), torch.tensor(box.face_normals[fi], dtype=torch.float32)


def test_candidates_surround_every_point_and_know_their_nearest_point():
    pts, _ = _box_points(300)
    cells, nearest = candidate_cells(pts, radius=1)
    own = ((pts.double() + 0.5) * LEVELS).floor().long()
    assert np.isin(flat_index(own).numpy(), flat_index(cells).numpy()).all()
    assert torch.equal(flat_index(cells), flat_index(cells).sort().values)  # sorted, unique
    u = (pts.double() + 0.5) * LEVELS
    brute = torch.cdist(cells.double() + 0.5, u).amin(1)
    # Each cell knows the points whose own cell is within the radius: the nearest of those.
    assert torch.allclose(nearest, brute) or (nearest >= brute - 1e-9).all()
    assert torch.allclose(nearest[nearest <= 1.0], brute[nearest <= 1.0])


def _neighbourhood(pts: torch.Tensor, nrm: torch.Tensor, cell: torch.Tensor, s: int):
    """The points (in cell units) and normals of the 3 x 3 x 3 coarse neighbourhood of ``cell`` at scale
    ``s``, or None when it holds none."""
    u = ((pts.double() + 0.5) * LEVELS).numpy()
    coarse = np.floor(u).clip(0, LEVELS - 1).astype(int) >> s
    near = (np.abs(coarse - (cell.numpy() >> s)) <= 1).all(1)
    return (u[near], nrm.double().numpy()[near]) if near.any() else None


def _features_by_loop(pts: torch.Tensor, nrm: torch.Tensor, cell: torch.Tensor, s: int) -> np.ndarray:
    """The features of one cell at scale ``s``, from the points of its 3 x 3 x 3 coarse neighbourhood."""
    hood = _neighbourhood(pts, nrm, cell, s)
    if hood is None:
        return np.zeros(10)
    p, n = hood
    mu = p.mean(0)
    evals = np.linalg.eigvalsh(np.cov(p.T, bias=True) + 1e-9 * np.eye(3))
    d = (mu - (cell.numpy() + 0.5)) / 2 ** s
    cov = np.cov(p.T, bias=True) / 4 ** s + (0.25 / 2 ** s) ** 2 * np.eye(3)
    maha = np.sqrt(d @ np.linalg.solve(cov, d))
    nvals = np.linalg.eigvalsh(n.T @ n / len(n))[::-1]
    return np.r_[np.log1p(len(p)), np.linalg.norm(d), np.log1p(maha), np.sqrt(evals.clip(0))[::-1] / 2 ** s,
                 nvals, 1.0]


def test_features_equal_a_loop_over_each_cells_neighbourhood():
    pts, nrm = _box_points(500)
    cells, nearest = candidate_cells(pts)
    feats = cell_features(pts, nrm, cells, nearest).double().numpy()
    rng = np.random.default_rng(0)
    for c in rng.choice(len(cells), 12, replace=False):
        for k, s in enumerate(SHIFTS):
            want = _features_by_loop(pts, nrm, cells[c], s)
            got = feats[c, 10 * k:10 * (k + 1)]
            assert np.allclose(got, want, atol=1e-4), (c, s)
    assert np.allclose(feats[:, -1], np.log1p(nearest.numpy()), atol=1e-6)


def _plane_fit_by_loop(pts: torch.Tensor, nrm: torch.Tensor, cell: torch.Tensor, s: int) -> np.ndarray:
    """The plane-fit features of one cell at scale ``s``: the planes of its neighbourhood's points, fitted by
    least squares in the directions the normals fix."""
    hood = _neighbourhood(pts, nrm, cell, s)
    if hood is None:
        return np.zeros(4)
    p, n = hood
    x = cell.numpy() + 0.5
    err = np.sqrt(np.mean(((x - p) * n).sum(1) ** 2))
    # argmin sum (n.(y - p))^2 over y = centroid + sum of the fixed directions
    a = n.T @ n / len(n)
    evals, evecs = np.linalg.eigh(a)
    fixed = evecs[:, evals > PLANE_FIT_RANK * evals[-1]]
    mu = p.mean(0)
    coef, *_ = np.linalg.lstsq(n @ fixed, ((p - mu) * n).sum(1), rcond=None)
    off = np.linalg.norm(x - (mu + fixed @ coef))
    return np.log1p([err, err / 2 ** s, off, off / 2 ** s])


def test_plane_fit_features_equal_a_least_squares_fit_per_neighbourhood():
    pts, nrm = _box_points(500)
    # Noisy normals, as a scan's: every direction is a little fixed, and only the truncation keeps the
    # weakly fixed ones at the centroid.
    nrm = torch.nn.functional.normalize(nrm + 0.05 * torch.randn(nrm.shape, generator=torch.Generator().manual_seed(0)))
    cells, nearest = candidate_cells(pts)
    feats = cell_features(pts, nrm, cells, nearest, plane_fit=True).double().numpy()
    assert feats.shape == (len(cells), n_features(True))
    assert np.array_equal(feats[:, :n_features()], cell_features(pts, nrm, cells, nearest).double().numpy())
    rng = np.random.default_rng(1)
    for c in rng.choice(len(cells), 12, replace=False):
        for k, s in enumerate(SHIFTS):
            got = feats[c, n_features() + 4 * k:n_features() + 4 * (k + 1)]
            assert np.allclose(got, _plane_fit_by_loop(pts, nrm, cells[c], s), atol=1e-4), (c, s)


def test_plane_fit_finds_a_box_corner():
    """At a corner the three faces' planes meet in one point: the fit lands in the corner's cell, and a cell
    on the crease six cells from it, whose neighbourhood holds the same three faces, is told apart."""
    pts, nrm = _box_points(4000)
    cells, nearest = candidate_cells(pts)
    feats = cell_features(pts, nrm, cells, nearest, plane_fit=True).double()
    corner = ((torch.tensor([0.25, 0.2, 0.15]) + 0.5) * LEVELS).floor().long()  # the box's (+, +, +) corner
    on_crease = corner - torch.tensor([1, 0, 6])  # inside the x and y faces' crease, 6 cells down
    k = SHIFTS.index(3)
    err, off = feats[:, n_features() + 4 * k].expm1(), feats[:, n_features() + 4 * k + 2].expm1()
    at, crease = (cells == corner).all(1), (cells == on_crease).all(1)
    assert at.sum() == 1 and crease.sum() == 1
    assert off[at].item() < 1.0 and err[at].item() < 1.0
    assert off[crease].item() > 4.0 and err[crease].item() > 1.5


def test_features_do_not_change_when_the_input_moves_by_whole_coarse_cells_or_turns_by_90_degrees():
    pts, nrm = _box_points(800)
    cells, nearest = candidate_cells(pts)
    base = cell_features(pts, nrm, cells, nearest, plane_fit=True)
    step = (1 << max(SHIFTS)) / LEVELS  # a whole coarse cell of the largest scale: every grid stays aligned
    moved = pts + torch.tensor([step, -step, 0.0])
    cm, nm = candidate_cells(moved)
    assert torch.equal(cm, cells + torch.tensor([1 << max(SHIFTS), -(1 << max(SHIFTS)), 0]))
    assert torch.allclose(cell_features(moved, nrm, cm, nm, plane_fit=True), base, atol=1e-4)
    # x -> y, y -> -x about the centre of the grid, which maps cells onto cells.
    turn = lambda p: torch.stack([-p[:, 1], p[:, 0], p[:, 2]], 1)  # noqa: E731
    t_pts, t_nrm = turn(pts), torch.stack([-nrm[:, 1], nrm[:, 0], nrm[:, 2]], 1)
    tc, tn = candidate_cells(t_pts)
    mapped = torch.stack([LEVELS - 1 - cells[:, 1], cells[:, 0], cells[:, 2]], 1)
    order = torch.argsort(flat_index(mapped))
    assert torch.equal(tc, mapped[order])
    assert torch.allclose(cell_features(t_pts, t_nrm, tc, tn, plane_fit=True), base[order], atol=1e-4)


def test_selection_takes_the_best_cells_and_never_two_neighbours():
    cells = torch.tensor([[5, 5, 5], [5, 5, 6], [6, 6, 6], [9, 9, 9], [20, 1, 1]])
    logits = torch.tensor([3.0, 5.0, 1.0, 0.5, -2.0])
    assert select_cells(cells, logits).tolist() == [[5, 5, 6], [9, 9, 9]]  # above 0: (5,5,5), (6,6,6) suppressed
    assert select_cells(cells, logits, count=3).tolist() == [[5, 5, 6], [9, 9, 9], [20, 1, 1]]
    assert select_cells(cells, logits, count=1).tolist() == [[5, 5, 6]]
    edge = torch.tensor([[0, 0, 0], [127, 127, 127], [1, 1, 1]])
    assert len(select_cells(edge, torch.tensor([1.0, 1.0, 0.5]))) == 2  # border cells index safely


def _snap_loop(q, grid, margin):
    """``snap_to_cells`` one vertex at a time: the slow twin."""
    out = []
    for x, y, z in np.asarray(q).tolist():
        own = float(grid[(x * LEVELS + y) * LEVELS + z])
        best, at = -np.inf, (x, y, z)
        for dx in (-1, 0, 1):
            for dy in (-1, 0, 1):
                for dz in (-1, 0, 1):
                    c = (x + dx, y + dy, z + dz)
                    if all(0 <= v < LEVELS for v in c) and float(grid[(c[0] * LEVELS + c[1]) * LEVELS + c[2]]) > best:
                        best, at = float(grid[(c[0] * LEVELS + c[1]) * LEVELS + c[2]]), c
        c = at if best > own + margin else (x, y, z)
        if list(c) not in out:
            out.append(list(c))
    return out


@pytest.mark.parametrize("margin", [0.0, 1.5, 100.0])
def test_snap_to_cells_equals_a_loop_over_each_vertex(margin):
    """Vertices move to the best of the 27 cells around them when it beats their own by the margin, those that
    meet become one (first vertex's place in the order), border cells included."""
    rng = np.random.default_rng(0)
    grid = np.full(LEVELS ** 3, FLOOR, dtype=np.float32)
    q = np.unique(np.concatenate([rng.integers(10, 14, (40, 3)), [[0, 0, 0], [127, 5, 127], [126, 127, 0]]]), axis=0)
    q = q[rng.permutation(len(q))]  # sequence order is not sorted order
    near = (q[:, None] + rng.integers(-1, 2, (len(q), 6, 3))).reshape(-1, 3).clip(0, LEVELS - 1)
    grid[flat_index(near)] = rng.normal(0, 3, len(near))
    got = snap_to_cells(q, torch.from_numpy(grid), margin)
    assert got.tolist() == _snap_loop(q, grid, margin)
    if margin == 0.0:
        assert len(got) < len(q)  # the cluster around (10..13)^3 merged
    if margin == 100.0:
        assert got.tolist() == q.tolist()
    assert snap_to_cells(np.zeros((0, 3), dtype=np.int64), grid, margin).shape == (0, 3)


def test_dense_grid_and_net_scores_line_up():
    pts, nrm = _box_points(600)
    net = CellNet(CellNetConfig(hidden=16, depth=1, n_points=600)).eval()
    cells, logits = net.score(pts, nrm)
    grid = net.grid(pts, nrm)
    assert grid.shape == (LEVELS ** 3,)
    assert torch.allclose(grid[flat_index(cells)], logits.clamp(min=FLOOR))
    off = torch.ones(LEVELS ** 3, dtype=torch.bool)
    off[flat_index(cells)] = False
    assert (grid[off] == FLOOR).all()
    assert torch.equal(dense_grid(cells, logits), grid)


def _decoder(seed: int = 0, counts: bool = False) -> VertexDecoder:
    torch.manual_seed(seed)
    enc = EncoderConfig(n_points=64, n_latents=4, dim=32, depth=1, heads=2, n_freqs=4, anchors=8)
    m = VertexDecoder(VertexConfig(dim=32, depth=2, heads=2, encoder=enc, evidence=True, evidence_normals=True,
                                   evidence_cells=True, evidence_counts=counts, count_condition=counts)).eval()
    with torch.no_grad():
        m.head.weight.normal_(0, 1.0)
        for t in (m.evidence.cell_block_table, m.evidence.cell_skip_table, m.evidence.cell_eos_table):
            t.weight.normal_(0, 3.0 / GAIN)
        if counts:
            for t in (m.evidence.stay_table, m.evidence.rest_table, m.evidence.count_table):
                t.weight.normal_(0, 3.0 / GAIN)
    return m


def _cell_grids(b: int, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    grid = torch.full((b, LEVELS ** 3), FLOOR)
    idx = torch.randint(0, LEVELS ** 3, (b, 400), generator=g)
    grid.scatter_(1, idx, torch.randn(b, 400, generator=g) * 4)
    return grid


def test_decoder_reads_the_cell_log_odds():
    m = _decoder()
    pts = torch.rand(2, 64, 3) - 0.5
    nrm = torch.nn.functional.normalize(torch.randn(2, 64, 3), dim=-1)
    grid = _cell_grids(2)
    with pytest.raises(ValueError, match="cell log-odds"):
        m.point_evidence(pts, nrm)
    base = m.point_evidence(pts, nrm, torch.full_like(grid, FLOOR))
    ev = m.point_evidence(pts, nrm, grid)
    block = torch.tensor([[-1, 7, 300], [0, 5, 511]])
    diff = ev.logit_bias(block) - base.logit_bias(block)
    for r in range(2):
        for t, b in enumerate(block[r].tolist()):
            if b < 0:
                assert diff[r, t, vt.OFFSET0:].abs().max() == 0  # no block yet: no offset evidence
                continue
            o = torch.arange(vt.N_OFFSETS)
            cell = join_cells(torch.full_like(o, b), o)
            want = m.evidence.cell_gain * (grid[r, flat_index(cell)] - FLOOR)
            assert torch.allclose(diff[r, t, vt.OFFSET0:], want, atol=1e-4)
    # The expected vertex count of a block is the sum of its cells' probabilities.
    p = torch.where(grid[0] > FLOOR, torch.sigmoid(grid[0]), 0.0).reshape(LEVELS, LEVELS, LEVELS)
    assert torch.allclose(ev.cell_expected[0, 7], p[0:16, 0:16, 112:128].sum(), rtol=1e-4)


@pytest.mark.parametrize("counts,target", [(False, None), (True, None), (True, (40, 0))])
def test_cached_equals_uncached_with_cell_evidence(counts, target):
    m = _decoder(3, counts)
    pts = torch.rand(2, 64, 3) - 0.5
    nrm = torch.nn.functional.normalize(torch.randn(2, 64, 3), dim=-1)
    target = None if target is None else torch.tensor(target)
    with torch.no_grad():
        prefix = m.condition(pts, nrm, target)
    ev = m.point_evidence(pts, nrm, _cell_grids(2, 1), target)
    cfg = SamplingConfig(temperature=0, max_vertices=10)
    cached = generate(m, prefix, cfg, evidence=ev)
    uncached = generate_uncached(m, prefix, max_vertices=10, evidence=ev, cfg=cfg)
    for a, b in zip(cached, uncached, strict=True):
        row = b.tolist()
        assert a.tolist() == (row[: row.index(vt.EOS) + 1] if vt.EOS in row else [t for t in row if t != vt.PAD])
    assert any(len(a) > 4 for a in cached)


def test_without_blocks_ahead_the_sequence_reads_the_cells_alone():
    """``evidence_blocks_ahead=False``: EOS and skipped blocks are priced in the cells' expected vertices only, so
    occupied blocks where the cells expect no vertex (a box's flat walls) cost nothing to leave out."""
    with pytest.raises(ValueError, match="occupied blocks or the cells"):
        PointEvidence(logodds=False, blocks_ahead=False)
    torch.manual_seed(0)
    enc = EncoderConfig(n_points=64, n_latents=4, dim=32, depth=1, heads=2, n_freqs=4, anchors=8)
    m = VertexDecoder(VertexConfig(dim=32, depth=2, heads=2, encoder=enc, evidence=True, evidence_cells=True,
                                   evidence_blocks_ahead=False)).eval()
    assert m.evidence.skip_table is None and m.evidence.eos_table is None
    with torch.no_grad():
        for t in (m.evidence.block_table, m.evidence.cell_block_table, m.evidence.cell_skip_table,
                  m.evidence.cell_eos_table):
            t.weight.normal_(0, 3.0 / GAIN)
    pts = torch.rand(1, 64, 3) - 0.5
    empty = torch.full((1, LEVELS ** 3), FLOOR)  # no candidate cell: no expected vertex anywhere
    ev = m.point_evidence(pts, None, empty)
    block = torch.tensor([[-1, 3, 200]])
    bias = ev.logit_bias(block)[0]
    none = GAIN * m.evidence.cell_eos_table.weight[0, 0]  # level 0: nothing expected ahead
    assert torch.allclose(bias[:, vt.EOS], none.expand(3))
    # A block token's bias: its occupancy level and the cells' tables, whatever it skips.
    occupancy = GAIN * (m.evidence.block_table(ev.levels[-1][0]).squeeze(-1)
                        + m.evidence.cell_block_table.weight[0, 0] + m.evidence.cell_skip_table.weight[0, 0])
    assert torch.allclose(bias[0, vt.BLOCK0:vt.OFFSET0], occupancy, atol=1e-5)


def test_count_reading_weighs_the_vertices_emitted_against_the_cells():
    """``evidence_counts``: staying in a block reads the vertices emitted in it against the block's expected
    vertices and those left after the current offset; EOS reads all vertices emitted against all expected.
    Checked per position against sums over the cells, taken one by one in sequence order."""
    import bisect

    from fastmesh.models.evidence import EXPECTED_LEVELS, RATIO_EDGES, RATIO_LEVELS, STAY_LEVELS
    from fastmesh.models.vertex import grammar_state, sequence_counts
    from fastmesh.tokenizer.grid import sort_key, unflat_index

    m = _decoder(5, counts=True)
    g = torch.Generator().manual_seed(2)
    grid = torch.full((1, LEVELS ** 3), FLOOR)  # candidates in the eight blocks of one 32-cell cube
    grid[0, flat_index(torch.randint(16, 48, (400, 3), generator=g))] = torch.randn(400, generator=g) * 4
    pts = torch.rand(1, 64, 3) - 0.5
    ev = m.point_evidence(pts, None if m.evidence.corner_table is None else torch.nn.functional.normalize(
        torch.randn(1, 64, 3), dim=-1), grid)
    # A sequence through some of the likeliest cells: several per block, several blocks.
    flat = grid[0].topk(40).indices
    cells = unflat_index(flat)
    tokens = torch.from_numpy(vt.encode(cells.numpy()))[None]
    block, offset = grammar_state(tokens)
    n_vert, n_in_block = sequence_counts(tokens)
    eos, stay = ev.count_bias(block, offset, n_vert, n_in_block)

    p = torch.where(grid[0] > FLOOR, torch.sigmoid(grid[0]), 0.0)
    cand = (p > 0).nonzero()[:, 0]
    keys, probs = sort_key(unflat_index(cand)), p[cand]
    total = float(probs.sum())

    def level(x, n):
        return min(int(np.floor(np.log2(1 + x))), n - 1)

    t_ = m.evidence
    seen_blocks, emitted, in_blk, checked = set(), 0, 0, 0
    for t, tok in enumerate(tokens[0].tolist()):
        if vt.BLOCK0 <= tok < vt.OFFSET0:
            seen_blocks.add(tok)
            in_blk = 0
        elif tok >= vt.OFFSET0:
            emitted, in_blk = emitted + 1, in_blk + 1
        b, o = int(block[0, t]), int(offset[0, t])
        if b < 0:
            assert eos[0, t] == 0 and stay[0, t] == 0
            continue
        in_block = float(probs[keys // vt.N_OFFSETS == b].sum())
        rest = float(probs[(keys // vt.N_OFFSETS == b) & (keys % vt.N_OFFSETS > o)].sum())
        assert (emitted, in_blk) == (int(n_vert[0, t]), int(n_in_block[0, t]))
        stay_row = level(in_blk, STAY_LEVELS) * EXPECTED_LEVELS + level(in_block, EXPECTED_LEVELS)
        want_stay = GAIN * (t_.stay_table.weight[stay_row] + t_.rest_table.weight[level(rest, EXPECTED_LEVELS)])
        ratio = bisect.bisect_left(RATIO_EDGES, np.log2(max(emitted, 0.5) / max(total, 1.0)))
        assert ratio < RATIO_LEVELS
        if not any(abs(x - round(x)) < 1e-3 for x in (in_block, rest)):  # sums in another order: same level
            checked += 1
            assert torch.allclose(stay[0, t], want_stay[0], atol=1e-4)
        assert torch.allclose(eos[0, t], GAIN * t_.count_table.weight[ratio, 0], atol=1e-4)
    assert len(seen_blocks) > 1 and int(n_in_block.max()) > 1 and checked > len(tokens[0]) // 2


def test_a_face_count_target_scales_what_the_cells_expect_to_it():
    from fastmesh.models.vertex import FACES_PER_VERTEX

    m = _decoder(6, counts=True)
    grid = _cell_grids(2, 3)
    pts = torch.rand(2, 64, 3) - 0.5
    nrm = torch.nn.functional.normalize(torch.randn(2, 64, 3), dim=-1)
    own = m.point_evidence(pts, nrm, grid)
    asked = m.point_evidence(pts, nrm, grid, torch.tensor([340, 0]))
    assert torch.allclose(asked.cell_cum[0, -1], torch.tensor(340 / FACES_PER_VERTEX))
    assert torch.allclose(asked.cell_cum[1], own.cell_cum[1])  # no target: the cells' own count
    scale = 340 / FACES_PER_VERTEX / own.cell_expected[0].sum()
    assert torch.allclose(asked.cell_expected[0], own.cell_expected[0] * scale, rtol=1e-4)
    assert asked.given.tolist() == [1, 0]
