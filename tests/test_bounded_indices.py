"""Every table lookup made from a computed value stays in its table, whatever the value.

On CUDA an index outside a table is a device-side assert that poisons the process; on the CPU it is an
IndexError.  Counts that come out a rounding below zero (float sums taken in another order), NaN, infinite
or huge must still give a valid row, and a whole generate with perturbed counts must give a valid mesh.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import fastmesh.models.evidence as evidence_module
from fastmesh.models.evidence import EXPECTED_LEVELS, POINT_LEVELS, SEQ_LEVELS, STAY_LEVELS, PointEvidence, _level
from fastmesh.models.generate import choose_next
from fastmesh.models.layers import CoordEmbedding
from fastmesh.models.vertex import VertexConfig, VertexDecoder
from fastmesh.params import SamplingConfig
from fastmesh.tokenizer import vertex as vt
from fastmesh.tokenizer.grid import LEVELS, N_BLOCKS, N_OFFSETS, quantize

BAD = [-0.5, -1e-7, -1.0, -3.0, float("nan"), float("inf"), float("-inf"), 1e30, -1e30]


@pytest.mark.parametrize("levels", [POINT_LEVELS, SEQ_LEVELS, EXPECTED_LEVELS, STAY_LEVELS])
def test_level_is_a_row_for_any_count(levels):
    counts = torch.tensor(BAD + [0.0, 0.4, 1.0, 2.0, 3.99, 1e6])
    lv = _level(counts, levels)
    assert lv.dtype == torch.int64
    assert int(lv.min()) >= 0 and int(lv.max()) <= levels - 1
    assert lv[4] == 0 and lv[0] == 0  # NaN, -0.5
    assert lv[BAD.index(float("inf"))] == levels - 1
    ints = torch.tensor([-(2 ** 40), -1, 0, 1, 2 ** 40])
    assert _level(ints, levels).tolist() == [0, 0, 0, 1, levels - 1]


def test_level_of_a_count_is_the_formula():
    """Counts >= 0 keep their level: min(floor(log2(1 + n)), L - 1), for integer and float counts alike."""
    n = torch.cat([torch.arange(0, 2000), torch.rand(500) * 300])
    want = [min(math.floor(math.log2(1 + float(x))), EXPECTED_LEVELS - 1) for x in n.float()]
    assert _level(n, EXPECTED_LEVELS).tolist() == want
    assert _level(n[:2000].long(), EXPECTED_LEVELS).tolist() == want[:2000]


def _evidence(target: float | None = None):
    """An Evidence of every kind of table (random weights, so every lookup shows in the bias), on a random shape."""
    torch.manual_seed(0)
    module = PointEvidence(normals=True, logodds=True, blocks_ahead=True, counts=True)
    for p in module.parameters():
        torch.nn.init.normal_(p)
    points = torch.rand(1, 300, 3) - 0.5
    normals = torch.nn.functional.normalize(torch.randn(1, 300, 3), dim=-1)
    cells = torch.randn(1, LEVELS ** 3) * 3
    return module(points, normals, cells, None if target is None else torch.tensor([target]))


STATES = {  # current block, offset, vertices emitted, of them in the block: in range and out of it
    "block": torch.tensor([[-1, 0, 5, N_BLOCKS - 1, N_BLOCKS + 88, -7]]),
    "offset": torch.tensor([[-1, 0, 4095, N_OFFSETS + 9, -5, 17]]),
    "n_vert": torch.tensor([[0, -3, 10 ** 12, 7, 1, 2]]),
    "n_in_block": torch.tensor([[0, -1, 10 ** 9, 3, 0, 2]]),
}


def _read_everything(ev) -> list[torch.Tensor]:
    block = STATES["block"]
    out = [ev.logit_bias(block)]
    out += list(ev.count_bias(block, STATES["offset"], STATES["n_vert"], STATES["n_in_block"]))
    for b in block[0, :, None]:  # the per-row readings, one state at a time
        out += [ev.weighted_cells(b, 6.0), ev.expected_through(b, 1.1), ev.offset_cells(b)]
    return out


@pytest.mark.parametrize("target", [None, 150.0])
@pytest.mark.parametrize("bad", BAD)
def test_every_evidence_lookup_takes_any_amount(bad, target):
    """The amounts the tables read (expected vertices per block, their running sums, occupied blocks) replaced
    by a bad value in some places: every reading still works and the tables' bias stays finite."""
    ev = _evidence(target)
    spots = torch.zeros_like(ev.cell_expected, dtype=torch.bool)
    spots[:, ::3] = True
    for name in ("cell_expected", "cell_incl", "cell_excl"):
        setattr(ev, name, torch.where(spots, torch.full_like(getattr(ev, name), bad), getattr(ev, name)))
    ev.cell_cum = torch.where(torch.rand(ev.cell_cum.shape) < 0.3, torch.tensor(bad), ev.cell_cum)
    shift = int(max(min(bad, 2 ** 40), -(2 ** 40))) if math.isfinite(bad) else -(2 ** 40)
    ev.occ_incl, ev.occ_excl = ev.occ_incl + shift, ev.occ_excl - 5
    bias, eos, stay = _read_everything(ev)[:3]
    assert bias.shape == (1, 6, vt.VOCAB_SIZE)
    assert torch.isfinite(bias).all() and torch.isfinite(eos).all() and torch.isfinite(stay).all()


def test_running_sums_a_rounding_apart_read_as_nothing_ahead():
    """The CUDA failure: at the last occupied block the expected amount ahead came out a rounding below 0."""
    ev = _evidence()
    ev.cell_expected = torch.zeros_like(ev.cell_expected)
    ev.cell_expected[0, [3, 40, 200]] = torch.tensor([0.7, 1.3, 0.45])
    ev.cell_incl = ev.cell_expected.cumsum(1)
    ev.cell_excl = ev.cell_incl - ev.cell_expected
    ev.cell_incl[0, 200] += 1e-6  # the running sum at the last occupied block a rounding above the total
    rows, block = torch.tensor([0]), torch.tensor([200])
    ahead, _ = evidence_module._ahead(ev.cell_incl, ev.cell_excl, rows, block)
    assert float(ahead) == 0.0
    assert torch.isfinite(ev.logit_bias(block[None])).all()


def test_quantize_puts_every_value_on_the_grid():
    v = [[float("nan"), float("inf"), float("-inf")], [0.0, -0.5, 0.4999], [1e30, -1e30, 0.49]]
    for q in (quantize(np.array(v)), quantize(torch.tensor(v)), quantize(torch.tensor(v).double())):
        q = np.asarray(q)
        assert q.dtype == np.int64 and q.min() >= 0 and q.max() <= LEVELS - 1
        assert q.tolist() == [[0, 127, 0], [64, 0, 127], [127, 0, 126]]


def test_coordinate_tables_read_cells_off_the_grid_at_the_border():
    emb = CoordEmbedding(8)
    out = emb(torch.tensor([[-3, 200, 5], [0, 127, 5]]))
    assert torch.equal(out[0], out[1])


def test_decoder_embeds_any_grammar_state():
    model = VertexDecoder(VertexConfig(dim=16, depth=1, heads=2, max_vertices=8))
    tokens = torch.tensor([[vt.BOS, vt.BLOCK0 + 3, vt.OFFSET0 + 4095, vt.EOS]])
    for block in ([[-1, 3, 3, 3]], [[-9, N_BLOCKS + 40, 10 ** 6, -1]]):
        assert torch.isfinite(model.embed(tokens, torch.tensor(block))).all()


def test_sampling_never_draws_a_nan_logit():
    logits = torch.zeros(2, vt.VOCAB_SIZE)
    logits[:, :vt.OFFSET0] = float("-inf")  # after a block token: offsets only
    logits[:, vt.OFFSET0:vt.OFFSET0 + 4000] = float("nan")
    gens = [torch.Generator().manual_seed(k) for k in range(2)]
    for _ in range(20):
        picked = choose_next(logits, SamplingConfig(temperature=1.0), gens)
        assert (picked >= vt.OFFSET0 + 4000).all()


def test_nan_cell_scores_are_no_candidates():
    """NaN log-odds read as FLOOR (no candidate), so the offsets' cell bias, added to the logits at every step,
    is finite."""
    from fastmesh.models.cells import FLOOR

    torch.manual_seed(0)
    module = PointEvidence(logodds=True, counts=True)
    cells = torch.randn(1, LEVELS ** 3)
    cells[:, ::2] = float("nan")
    ev = module(torch.rand(1, 300, 3) - 0.5, None, cells)
    assert torch.equal(ev.logodds[:, ::2], torch.full_like(ev.logodds[:, ::2], FLOOR))
    assert torch.equal(ev.logodds[:, 1::2], cells[:, 1::2])
    for block in range(0, N_BLOCKS, 37):
        assert torch.isfinite(ev.weighted_cells(torch.tensor([block]), 6.0)).all()
    assert torch.isfinite(ev.cell_cum).all() and torch.isfinite(ev.cell_expected).all()


def test_sampling_with_no_finite_logit_is_a_clear_error():
    logits = torch.full((1, vt.VOCAB_SIZE), float("nan"))
    with pytest.raises(FloatingPointError, match="no token"):
        choose_next(logits, SamplingConfig(temperature=1.0), [torch.Generator().manual_seed(0)])


@pytest.fixture(scope="module")
def shipped():
    from fastmesh.pipeline import Pipeline

    return Pipeline.from_pretrained(device="cpu")


@pytest.mark.parametrize("delta", [-0.5, float("nan")])
def test_generate_with_perturbed_counts_gives_a_mesh(shipped, monkeypatch, delta):
    """The shipped weights (cells, counts and sequence tables) end to end, every other count read by a table
    moved by ``delta`` first (all of them NaN would read as "nothing anywhere" and end the sequence at once): the
    decode completes with a valid mesh."""
    from fastmesh.evaluation.primitives import point_cloud, primitive
    from fastmesh.pipeline import GenerateParams

    exact = evidence_module._level

    def perturbed(count, levels):
        every_other = torch.arange(count.numel()).reshape(count.shape) % 2 == 0
        return exact(torch.where(every_other, count.double() + delta, count.double()), levels)

    monkeypatch.setattr(evidence_module, "_level", perturbed)
    res = shipped.generate(point_cloud(primitive("l_block"), n=2048), GenerateParams(seed=0, candidates=1,
                                                                                      max_vertices=40))
    _assert_valid(res)


def test_generate_with_nan_cell_scores_gives_a_mesh(shipped, monkeypatch):
    """A third of the cell network's log-odds NaN: those cells are never drawn, the rest decodes as usual."""
    from fastmesh.evaluation.primitives import point_cloud, primitive
    from fastmesh.pipeline import GenerateParams

    grid = shipped.cell_net.grid

    def poisoned(*args, **kwargs):
        g = grid(*args, **kwargs).clone()
        g.view(-1)[::3] = float("nan")
        return g

    monkeypatch.setattr(shipped.cell_net, "grid", poisoned)
    res = shipped.generate(point_cloud(primitive("box"), n=2048), GenerateParams(seed=1, candidates=1,
                                                                                  max_vertices=40))
    _assert_valid(res)


def _assert_valid(res) -> None:
    assert len(res.faces) > 0 and np.isfinite(res.vertices).all()
    assert res.faces.min() >= 0 and res.faces.max() < len(res.vertices)
