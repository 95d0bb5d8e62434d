"""The pipeline API and ``fastmesh generate``, on tiny random networks (seconds), plus one
smoke test of the shipped weights end to end."""

from __future__ import annotations

import io
import json
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh

from fastmesh.evaluation.primitives import point_cloud
from fastmesh.evaluation.quality import mesh_quality
from fastmesh.faces import mesh_from_adjacency
from fastmesh.faces.filtering import FilterConfig
from fastmesh.faces.support import surface_fit
from fastmesh.faces.triangles import TriangleConfig
from fastmesh.fitting import FitConfig
from fastmesh.params import GenerateParams
from fastmesh.pipeline import RANDOM_SURFACE_TOL, Cancelled, GenerationError, Pipeline, default_weights_dir
from fastmesh.pipeline.settings import read_settings, write_settings
from fastmesh.shapes.io import load_shape, sample_surface
from fastmesh.shapes.shape import Shape
from fastmesh.tokenizer.grid import CELL

torch.set_num_threads(1)


@pytest.fixture(scope="module")
def pipe() -> Pipeline:
    return Pipeline.random(seed=0)


def _sphere(center=(10.0, -4.0, 2.0), scale=3.0) -> Shape:
    """A dense mesh (1,280 faces): more than the tiny networks' results, which a low-poly input would replace."""
    m = trimesh.creation.icosphere(3)
    return Shape(vertices=np.asarray(m.vertices) * scale + np.asarray(center), faces=np.asarray(m.faces))


def test_generate_returns_mesh_in_input_frame(pipe):
    shape = _sphere()
    res = pipe.generate(shape, GenerateParams(seed=1, max_vertices=24))
    assert res.faces.shape[1] == 3 and len(res.faces) > 0
    assert res.faces.max() < len(res.vertices)
    lo, hi = shape.bounds
    # Outputs are back in the input's frame: inside its bounding box (plus half a 7-bit cell).
    tol = (hi - lo).max() * CELL
    assert (res.vertices >= lo - tol).all() and (res.vertices <= hi + tol).all()
    assert set(res.timings) == {"encode", "vertices", "enhancer", "faces", "filtering", "weighing"}
    assert all(v >= 0 for v in res.timings.values())
    # BOS, >= 1 block token, offsets, EOS (the result may hold more: a pinched vertex splits into one per fan)
    assert res.tokens >= 3 + res.info["generated_vertices"]
    # The Python API result carries the quality report of exactly this mesh against this input, and the
    # closure's decision: the sphere is a closed mesh.
    assert res.quality == {**mesh_quality(res.vertices, res.faces, shape), "closed_decision": "closed",
                           "faces": len(res.faces), "target_faces": None, "target_met": None, "count_step": None,
                           "quads": 0, "quad_share": 0.0}
    assert res.quality["cd"] > 0 and res.quality["components"] >= 1
    assert res.info["closed_decision"] == {"close": True, "reason": "closed_mesh"}


def test_a_low_poly_mesh_input_comes_back_as_it_is_or_at_the_count_asked(pipe):
    """A mesh with fewer faces than the result (here the 12 of a box split at its seams, as files store
    it) is returned welded: never more faces than a low-poly input.  A face-count target is a request: the
    input's own surface split to it, closed and exact, without the networks."""
    m = trimesh.creation.box(extents=(1.0, 2.0, 0.5))
    split = Shape(vertices=m.vertices[m.faces].reshape(-1, 3) + 100.0, faces=np.arange(36).reshape(-1, 3))
    res = pipe.generate(split, GenerateParams(seed=0, max_vertices=24))
    assert res.info["result_from"] == "input" and len(res.vertices) == 8 and len(res.faces) == 12
    assert res.quality["watertight"] and res.quality["hd"] == 0.0
    asked = pipe.generate(split, GenerateParams(seed=0, max_vertices=24, target_faces=40))
    assert asked.info["result_from"] == "input" and asked.tokens == 0
    assert asked.quality["count_step"] == "split" and asked.quality["target_met"] and len(asked.faces) >= 40
    assert asked.quality["watertight"] and asked.info["faces_before_count"] == 12
    on = trimesh.Trimesh(asked.vertices - 100.0, asked.faces, process=False)
    assert np.isclose(on.area, m.area) and np.isclose(on.volume, m.volume)  # the box's own surface, no fold
    assert np.abs(np.abs(on.vertices) - m.extents / 2).min(1).max() < 1e-9  # every vertex on a side
    dense = pipe.generate(_sphere(), GenerateParams(seed=0, max_vertices=24))
    assert dense.info["result_from"] == "model" and len(dense.faces) < 1280


def test_a_turned_shape_is_also_made_in_its_canonical_frame(pipe, monkeypatch):
    """A box turned at an angle is made in its own frame and in its oriented box's, each turned back to the
    input's frame; an axis-aligned one only once."""
    from fastmesh.shapes.canonical import canonical_rotation, frame_normals

    calls = []
    made = pipe._frame

    def spy(shape, rotation, *args):
        calls.append(rotation)
        return made(shape, rotation, *args)

    from fastmesh.pipeline import result as step8

    monkeypatch.setattr(pipe, "_frame", spy)
    # A dense box would be simplified within its own faces (test_flat), with no frame made.
    monkeypatch.setattr(step8, "flat_faced", lambda req: None)
    box = trimesh.creation.box(extents=(3.0, 2.0, 1.0)).subdivide().subdivide()  # 192 faces: no low-poly input
    turn = trimesh.transformations.rotation_matrix(0.6, [1.0, 2.0, 3.0])
    turned = box.copy()
    turned.apply_transform(turn)
    shape = Shape(vertices=np.asarray(turned.vertices), faces=np.asarray(turned.faces))
    # closed=false: a box closed would be rebuilt from its planes (test_planar), with no frame made
    res = pipe.generate(shape, GenerateParams(seed=0, max_vertices=24, candidates=1, closed="false"))
    expected = canonical_rotation(shape.vertices, frame_normals(shape))
    assert len(calls) == 2 and np.array_equal(calls[0], np.eye(3)) and np.array_equal(calls[1], expected)
    assert np.allclose(expected @ turn[:3, :3], np.eye(3), atol=1e-6)  # the box's own axes, as built
    lo, hi = shape.bounds
    assert (res.vertices >= lo - 0.05).all() and (res.vertices <= hi + 0.05).all()  # back in the input frame
    assert res.info["turned_degrees"] in (0.0, round(np.degrees(0.6), 3))
    calls.clear()
    pipe.generate(Shape(vertices=np.asarray(box.vertices), faces=np.asarray(box.faces)),
                  GenerateParams(seed=0, max_vertices=24, candidates=1, closed="false"))
    assert len(calls) == 1


def test_same_seed_same_mesh_and_save_load_roundtrip(pipe, weights):
    shape = _sphere()
    a = pipe.generate(shape, GenerateParams(seed=3, max_vertices=20, temperature=1.0))
    b = Pipeline.from_pretrained(weights).generate(shape, GenerateParams(seed=3, max_vertices=20, temperature=1.0))
    assert np.allclose(a.vertices, b.vertices) and np.array_equal(a.faces, b.faces)


def test_what_ships_is_what_the_defaults_build(tmp_path):
    """The shipped ``pipeline.json`` is the code's defaults, written whole: the shipped pipeline, a random one
    and one saved and loaded again all run the same settings."""
    shipped = Pipeline.from_pretrained()
    defaults = {"filter_config": FilterConfig(), "triangle_config": TriangleConfig(), "fit_config": FitConfig()}
    assert {name: getattr(shipped, name) for name in defaults} == defaults
    # A random pipeline runs the same face stage, with a support limit as wide as the input.
    random = Pipeline.random(seed=0)
    assert random.filter_config == FilterConfig() and random.fit_config == FitConfig()
    assert random.triangle_config == TriangleConfig(surface_tol=RANDOM_SURFACE_TOL, weigh_decimation=False,
                                                     redistribute=None, refine=None, swap_edges=False,
                                                     add_missed=None, quadric_vertices=False, reach_extent=False,
                                                     outline=False, coarsen=None)
    written = tmp_path / "pipeline.json"
    write_settings(written, **defaults)
    assert json.loads(written.read_text()) == json.loads((default_weights_dir() / "pipeline.json").read_text())
    assert read_settings(written) == defaults


def test_the_shipped_decoder_is_the_named_one():
    """``VertexConfig.from_name("shipped")`` builds the decoder of the shipped weights, flags and sizes."""
    from fastmesh.models.vertex import VertexConfig

    assert Pipeline.from_pretrained().vertex.cfg == VertexConfig.from_name("shipped")
    with pytest.raises(ValueError, match="shipped"):
        VertexConfig.from_name("large")


def test_settings_refuse_an_unknown_section_or_key(tmp_path):
    path = tmp_path / "pipeline.json"
    path.write_text(json.dumps({"note": "prose"}))
    with pytest.raises(ValueError, match="note"):
        read_settings(path)
    path.write_text(json.dumps({"faces": {"model_triangles": True}}))
    with pytest.raises(TypeError, match="model_triangles"):
        read_settings(path)


def test_filtering_and_cleanup_settings_survive_save_load(tmp_path):
    p = Pipeline.random(seed=0)
    p.filter_config = FilterConfig(first_threshold=0.6, final_threshold=0.4, candidate_passes=1)
    p.triangle_config = TriangleConfig(remove_unreferenced=True, drop_coplanar_diagonals=True, support_tol=0.02,
                                       flat_tol=None)
    p.fit_config = FitConfig(radius=3.0, rel=0.1, points=1000, spacings=2.0, reach=None, merge=0.5)
    p.save(tmp_path)
    q = Pipeline.from_pretrained(tmp_path)
    assert q.filter_config == p.filter_config and q.triangle_config == p.triangle_config
    assert q.fit_config == p.fit_config


def test_vertices_are_fitted_to_the_input_planes_unless_off(pipe):
    """The fit moves the enhancer's positions onto the box's planes; radius None leaves them.  (Its points: the
    box's own 12 faces are fewer than any result, and come back as they are.)"""
    box = point_cloud(Shape(vertices=np.asarray(trimesh.creation.box().vertices),
                            faces=np.asarray(trimesh.creation.box().faces)), 4000)
    params = GenerateParams(seed=0, max_vertices=24, closed="false")  # not rebuilt from its planes
    saved, tc = pipe.fit_config, pipe.triangle_config
    try:
        # The surface selection keeps the decoder's vertices as fitted (the solid adds input samples of its own).
        pipe.triangle_config = replace(tc, solid=None)
        fitted = pipe.generate(box, params)
        pipe.fit_config = FitConfig(radius=None)
        loose = pipe.generate(box, params)
    finally:
        pipe.fit_config, pipe.triangle_config = saved, tc

    def near_but_off(v):  # within a 7-bit cell of a face plane of the box but not on it
        d = np.abs(0.5 - np.abs(v)).min(axis=1)
        return ((d > 1e-9) & (d < CELL)).sum()

    assert near_but_off(loose.vertices) > 0 and near_but_off(fitted.vertices) == 0


def test_vertices_fitted_onto_one_point_become_one(monkeypatch):
    """With the shipped weights the fit puts several decoded vertices of the L block on one corner; with
    ``FitConfig.merge`` the face stage gets one of each such cluster, with None all of them; and the input
    points added to a mesh's vertices (step 7, ``TriangleConfig.add_missed``) never land on one either."""
    from dataclasses import replace

    from scipy.spatial import cKDTree

    import fastmesh.pipeline.candidate as pipeline_module
    from fastmesh.evaluation.primitives import point_cloud, primitive

    seen = []

    def spy(positions, *args, **kwargs):
        seen.append(len(cKDTree(positions).query_pairs(0.1 * CELL)))  # the normalised frame: cells
        return mesh_from_adjacency(positions, *args, **kwargs)

    monkeypatch.setattr(pipeline_module, "mesh_from_adjacency", spy)
    pipe = Pipeline.from_pretrained()
    cloud = point_cloud(primitive("l_block"))
    params = GenerateParams(seed=0, candidates=1, closed="false")  # not rebuilt from its planes
    pipe.fit_config = replace(pipe.fit_config, merge=None)
    kept = pipe.generate(cloud, params)
    runs = len(seen)
    pipe.fit_config = replace(pipe.fit_config, merge=0.1)
    merged = pipe.generate(cloud, params)
    assert seen[0] > 0 and seen[runs:] == [0] * (len(seen) - runs)
    assert merged.info["generated_vertices"] == kept.info["generated_vertices"]  # the decoder's count


def test_vertices_merged_below_three_are_a_clear_error(monkeypatch):
    """A candidate whose vertices the fit puts on fewer than three points makes no mesh: a GenerationError,
    not a crash in the face stage."""
    import fastmesh.pipeline.candidate as pipeline_module

    monkeypatch.setattr(pipeline_module, "distinct", lambda positions, tol: np.arange(min(2, len(positions))))
    pipe = Pipeline.random(seed=0)
    with pytest.raises(GenerationError, match="lie on 2 points") as err:
        pipe.generate(_sphere(), GenerateParams(seed=0, max_vertices=20, candidates=1))
    assert err.value.code == "no_vertices"


def test_flat_vertices_go_except_with_a_face_count_target_told(pipe):
    """``TriangleConfig.flat_tol`` removes vertices on the box's faces; a ``target_faces`` told to the decoder
    keeps them (it made them for that count).  The box as points: its own 12 faces would come back as they are."""
    from dataclasses import replace

    from fastmesh.params import TunedParams

    box = point_cloud(Shape(vertices=np.asarray(trimesh.creation.box().vertices),
                            faces=np.asarray(trimesh.creation.box().faces)), 4000)
    saved = pipe.triangle_config
    surface = TriangleConfig()  # as shipped
    runs = {}
    try:
        for tol in (surface.flat_tol, None):
            pipe.triangle_config = replace(surface, flat_tol=tol)
            for target in (None, 40):
                runs[tol is None, target] = pipe.generate(box, TunedParams({"read_count": True}, GenerateParams(
                    seed=0, max_vertices=24, target_faces=target, closed="false")))
    finally:
        pipe.triangle_config = saved
    assert len(runs[False, None].vertices) < len(runs[True, None].vertices)
    assert np.array_equal(runs[False, 40].faces, runs[True, 40].faces)
    assert np.array_equal(runs[False, 40].vertices, runs[True, 40].vertices)


def test_candidates_return_the_one_nearest_the_input(pipe, monkeypatch):
    """candidates=K makes the meshes of seeds s, s+1, ..., s+K-1 and returns the best fit to the input;
    the chosen one is exactly what its seed gives alone."""
    import fastmesh.pipeline.result as fp

    # Candidates are scored before the whole step; the random networks' strays would be pulled in after it.
    monkeypatch.setattr(fp, "pull_in", lambda vertices, surface, limit: (vertices, np.zeros(len(vertices), bool)))
    shape = _sphere()
    many = pipe.generate(shape, GenerateParams(seed=5, max_vertices=24, temperature=1.0, candidates=4))
    fits = many.info["fits"]
    assert many.info["candidates"] == 4 and len(fits) == 4 and len(set(fits)) > 1  # they differ
    made = [np.inf if fit is None else fit for fit in fits]  # None: that candidate made no mesh
    chosen = many.info["chosen_seed"]
    assert chosen == 5 + int(np.argmin(made))
    alone = pipe.generate(shape, GenerateParams(seed=chosen, max_vertices=24, temperature=1.0, candidates=1))
    assert alone.info["candidates"] == 1 and alone.info["chosen_seed"] == chosen and "fits" not in alone.info
    assert np.allclose(many.vertices, alone.vertices) and np.array_equal(many.faces, alone.faces)
    # The fit is the Chamfer distance to the input's samples, in the unit cube.
    scale = (shape.bounds[1] - shape.bounds[0]).max()
    fit = surface_fit(many.vertices / scale, many.faces, sample_surface(shape, 16384, seed=5)[0] / scale, seed=5)
    assert fit == pytest.approx(min(made), rel=1e-3)
    # Greedy decoding has one answer: no candidates are drawn.
    greedy = pipe.generate(shape, GenerateParams(seed=5, max_vertices=24, temperature=0, candidates=4))
    assert greedy.info["candidates"] == 1


@pytest.mark.parametrize("bad", [0, 17, 2.5])
def test_candidates_out_of_range_is_a_clear_error(pipe, bad):
    with pytest.raises(ValueError, match="candidates"):
        pipe.generate(_sphere(), GenerateParams(candidates=bad))


def test_max_vertices_is_respected(pipe):
    res = pipe.generate(_sphere(), GenerateParams(seed=0, max_vertices=5, temperature=0))
    assert res.info["generated_vertices"] <= 5


def test_point_cloud_input(pipe):
    sphere = _sphere()
    pts, nrm = sample_surface(sphere, 500, seed=0)
    res = pipe.generate(Shape(vertices=pts.astype(np.float64), normals=nrm.astype(np.float64)),
                        GenerateParams(max_vertices=16))
    assert len(res.faces) > 0


def test_progress_is_monotone_and_completes(pipe):
    seen = []
    pipe.generate(_sphere(), GenerateParams(max_vertices=40, temperature=1.0),
                  progress=lambda stage, f: seen.append((stage, f)))
    fractions = [f for _, f in seen]
    assert fractions == sorted(fractions) and fractions[-1] == 1.0
    stages = [s for s, _ in seen]
    assert stages[0] == "encode" and "vertices" in stages


def test_cancel_raises(pipe):
    with pytest.raises(Cancelled):
        pipe.generate(_sphere(), GenerateParams(max_vertices=40), should_cancel=lambda: True)


def test_cancel_is_heard_where_no_network_runs(pipe):
    """A dense box rebuilt from its planes: a cancel asked meanwhile stops the job, not a result (the flat path:
    ``test_flat``)."""
    box = trimesh.creation.box(extents=(3.0, 2.0, 1.0)).subdivide().subdivide()
    shape = Shape(vertices=np.asarray(box.vertices), faces=np.asarray(box.faces))
    params = GenerateParams(max_vertices=24)
    assert pipe.generate(shape, params).info["result_from"] == "planes"
    with pytest.raises(Cancelled):
        pipe.generate(shape, params, should_cancel=lambda: True)


@pytest.mark.parametrize("bad", [dict(temperature=-1), dict(top_p=0), dict(top_k=-2), dict(max_vertices=2),
                                 dict(max_vertices=10**6), dict(seed=-1), dict(target_faces=3),
                                 dict(target_faces=10**5), dict(target_faces=1.5)])
def test_bad_params_raise_value_error(pipe, bad):
    with pytest.raises(ValueError):
        pipe.generate(_sphere(), GenerateParams(**bad))


def test_target_faces_reaches_the_decoder_only_where_it_is_told(pipe):
    """Untold, a face-count target leaves the decoder as it is (the same tokens as without one: the result is
    brought to the count afterwards); told (``SamplingConfig.read_count``), it reaches the decoder's count token
    and changes what is sampled (a random decoder follows no target, but must read it), and a decoder without
    the token refuses it up front."""
    from fastmesh.params import TunedParams

    shape = _sphere()
    plain = pipe.generate(shape, GenerateParams(seed=1, candidates=1))
    assert plain.faces.tolist() == pipe.generate(shape, GenerateParams(seed=1, candidates=1,
                                                                       target_faces=None)).faces.tolist()
    saved = pipe.vertex.count_emb.weight.detach().clone()
    with torch.no_grad():
        pipe.vertex.count_emb.weight.normal_(0, 3.0)
    try:
        made = {(told, target): pipe.generate(shape, TunedParams(
            {"read_count": told, "tell_below": 0.0}, GenerateParams(seed=1, candidates=1, target_faces=target)))
            for told in (False, True) for target in (None, 20, 4000)}
    finally:
        with torch.no_grad():
            pipe.vertex.count_emb.weight.copy_(saved)
    plain = made[False, None]  # the count token's "model's choice" is random too
    for target in (20, 4000):
        assert made[False, target].tokens == plain.tokens
        assert made[False, target].info["generated_vertices"] == plain.info["generated_vertices"]
        assert made[False, target].info["faces_before_count"] == len(plain.faces)
    small, large = made[True, 20], made[True, 4000]
    assert small.info["generated_vertices"] != large.info["generated_vertices"] or \
        small.vertices.tolist() != large.vertices.tolist()
    blind = Pipeline.random(seed=0)
    blind.vertex.cfg.count_condition = False
    assert len(blind.generate(shape, GenerateParams(candidates=1, target_faces=300)).faces) > 0
    with pytest.raises(ValueError, match="target_faces"):
        blind.generate(shape, TunedParams({"read_count": True}, GenerateParams(target_faces=300)))


def test_a_target_far_under_the_cells_count_is_told_to_the_decoder(pipe, monkeypatch):
    """By default the decoder is told a target only under ``tell_below`` x the vertices the cells expect (their
    probabilities' sum, cells at FLOOR none), where it has a count token and cells to read; then the whole
    request reads the told count rule (no snap, no flat vertex removed) and every candidate's prefix the count."""
    from fastmesh.faces.facecount import count_rule
    from fastmesh.models.cells import FLOOR
    from fastmesh.params import SamplingConfig, TunedParams

    cells = torch.full((1, 128 ** 3), FLOOR)
    cells[0, :400] = 0.0  # 400 cells of probability 1/2: 200 vertices expected

    def told(target, logodds=cells, **settings):
        return pipe.tells(TunedParams(settings, GenerateParams(target_faces=target)), logodds)

    assert SamplingConfig().tell_below == 0.5 and not SamplingConfig().read_count
    assert told(99) and not told(100) and not told(4000)
    assert not told(99, tell_below=0.0) and told(4000, read_count=True)
    assert not told(99, logodds=None) and told(99, logodds=None, read_count=True)
    assert not pipe.tells(GenerateParams(), cells)
    blind = Pipeline.random(seed=0)
    blind.vertex.cfg.count_condition = False
    assert not blind.tells(GenerateParams(target_faces=99), cells)

    seen = []
    monkeypatch.setattr(pipe, "_logodds", lambda frame, params, corners=None: cells)
    monkeypatch.setattr(pipe.vertex, "condition", lambda p, n, target: seen.append(target) or torch.zeros(1, 1, 1))
    monkeypatch.setattr(pipe.vertex, "point_evidence", lambda *args: None)
    monkeypatch.setattr(pipe, "_decode", lambda req, frames, report: _stop(req))
    for target, want in ((99, True), (150, False), (None, False)):
        seen.clear()
        with pytest.raises(_Stop) as stop:
            pipe.generate(_sphere(), GenerateParams(candidates=2, target_faces=target))
        assert stop.value.req.count == count_rule(target, told=want)
        assert [None if t is None else int(t) for t in seen] == [target if want else None] * 2


class _Stop(Exception):
    def __init__(self, req):
        self.req = req


def _stop(req):
    raise _Stop(req)
    yield  # a generator, as ``_decode`` is


def test_vertex_cells_move_by_the_cells_only_when_asked_and_without_a_told_target(pipe):
    """``Pipeline.vertex_cells``: the tokens' cells as they are, unless ``snap_margin`` is set and no face-count
    target is told to the decoder: then ``models.cells.snap_to_cells`` of them."""
    from fastmesh.models.cells import FLOOR, snap_to_cells
    from fastmesh.params import SamplingConfig, TunedParams
    from fastmesh.tokenizer import vertex as vt

    def snapping(told=False, **fields):
        return TunedParams({"snap_margin": 0.5, "read_count": told}, GenerateParams(**fields))

    q = np.array([[3, 4, 5], [3, 4, 6], [40, 40, 40]])
    tokens = vt.encode(q)
    cells = torch.full((1, 128 ** 3), FLOOR)
    cells[0, (3 * 128 + 5) * 128 + 6] = 2.0  # beside both of the first two: they meet there
    assert SamplingConfig().snap_margin == GenerateParams().sampling(100).snap_margin is not None  # on by default
    assert pipe.vertex_cells(tokens, cells, TunedParams({"snap_margin": None})).tolist() == vt.decode(tokens).tolist()
    assert pipe.vertex_cells(tokens, None, snapping()).tolist() == vt.decode(tokens).tolist()
    assert pipe.vertex_cells(tokens, cells, snapping(True, target_faces=100)).tolist() == vt.decode(tokens).tolist()
    moved = pipe.vertex_cells(tokens, cells, snapping())
    assert pipe.vertex_cells(tokens, cells, snapping(target_faces=100)).tolist() == moved.tolist()
    assert moved.tolist() == snap_to_cells(vt.decode(tokens), cells[0], 0.5).tolist() == [[3, 5, 6], [40, 40, 40]]


def test_no_faces_is_a_generation_error(pipe):
    # A face model that connects nothing must fail loudly, not return an empty mesh: under the paper's rule (the
    # shipped selection still finds the input's surface triangles, which the model only scores).
    from dataclasses import replace

    # A point cloud's solid face stage labels cells by the input's winding numbers: it has faces however the
    # network scores; a mesh input (the sphere here) has no solid stage.
    silent = Pipeline.random(seed=0)
    silent.triangle_config = replace(silent.triangle_config, selection="cliques")
    with torch.no_grad():
        silent.face.edge_out.bias.fill_(-20.0)
    with pytest.raises(GenerationError) as e:
        silent.generate(_sphere(), GenerateParams(max_vertices=16))
    assert e.value.code == "no_faces"
    cloud = point_cloud(_sphere(), 4096)
    solid = silent.generate(cloud, GenerateParams(max_vertices=16))
    assert len(solid.faces) and solid.info["solid_fits"]["faces_from"] == "solid"


def test_pipeline_chooses_its_thread_count(monkeypatch):
    """The Python API is as fast as the CLI without any set-up: 1 torch thread on CPU unless told otherwise."""
    monkeypatch.delenv("FASTMESH_TORCH_THREADS", raising=False)
    torch.set_num_threads(2)  # torch's own default on a 2-core machine, many times slower under load
    try:
        p = Pipeline.random(seed=0, device="cpu")
        assert torch.get_num_threads() == 1 and p.info()["threads"] == 1
        Pipeline.random(seed=0, device="cpu", threads=2)
        assert torch.get_num_threads() == 2
        monkeypatch.setenv("FASTMESH_TORCH_THREADS", "3")
        assert Pipeline.random(seed=0, device="cpu").info()["threads"] == 3
        assert Pipeline.random(seed=0, device="cpu", threads=1).info()["threads"] == 1  # the argument wins
        monkeypatch.setenv("FASTMESH_TORCH_THREADS", "two")
        with pytest.raises(ValueError, match="FASTMESH_TORCH_THREADS"):
            Pipeline.random(seed=0, device="cpu")
    finally:
        torch.set_num_threads(1)


def _cli(*args, check=True):
    return subprocess.run([sys.executable, "-m", "fastmesh.cli", *args], capture_output=True, text=True,
                          check=check, timeout=300)


def test_cli_generate_file_json(tmp_path, weights):
    src = tmp_path / "ball.obj"
    trimesh.Trimesh(*[getattr(_sphere(), k) for k in ("vertices", "faces")]).export(src)
    out = tmp_path / "out.glb"
    r = _cli("generate", str(src), "-o", str(out), "--weights", weights, "--max-vertices", "20", "--json")
    rec = json.loads(r.stdout.strip().splitlines()[-1])
    assert set(rec) == {"input", "output", "vertices", "faces", "tokens", "timings", "result_from", "vertices_from",
                        "quality", "placement", "notes"}
    assert rec["result_from"] == "model"  # the tiny networks' weights do not weigh the decimation
    assert rec["vertices_from"] == "decoder"  # nor the quadrics' vertices
    assert set(rec["quality"]) == {"cd", "hd", "boundary_edges", "non_manifold_edges", "non_manifold_vertices",
                                   "components", "pieces", "input_pieces", "watertight", "box_gap", "closed_decision",
                                   "faces", "target_faces", "target_met", "count_step", "quads", "quad_share",
                                   "back_face_share", "misoriented_edges", "misoriented_area", "self_intersections",
                                   "unwelded_vertices"}
    assert rec["quality"]["quad_share"] == 0.0 and rec["notes"] == []  # triangles, in the input's frame
    assert rec["placement"] == {"scale": 1.0, "offset": [0.0, 0.0, 0.0], "up": "y"}
    assert set(rec["timings"]) == {"load", "encode", "vertices", "enhancer", "faces", "filtering", "weighing",
                                   "export", "total"}
    mesh = trimesh.load(out, force="mesh")
    assert len(mesh.faces) == rec["faces"] > 0


def test_cli_generate_directory(tmp_path, weights):
    src = tmp_path / "in"
    src.mkdir()
    sphere = _sphere()
    pts, nrm = sample_surface(sphere, 300, seed=0)
    np.save(src / "a.npy", np.concatenate([pts, nrm], axis=1))
    trimesh.Trimesh(sphere.vertices, sphere.faces).export(src / "b.ply")
    (src / "broken.obj").write_text("v 1 2\nf 1 2 3\n")
    out = tmp_path / "out"
    r = _cli("generate", str(src), "-o", str(out), "--weights", weights, "--max-vertices", "12",
             "--format", "obj", check=False)
    assert r.returncode == 1  # one input failed ...
    assert "broken.obj" in r.stderr
    assert (out / "a.npy.obj").exists() and (out / "b.ply.obj").exists()  # ... the others were done
    assert r.stderr.count("[") >= 3  # one progress line per file


def test_cli_generate_directory_same_stem_two_outputs(tmp_path, weights):
    """Wuson.off and Wuson.ply are two inputs: two results, neither overwriting the other."""
    src = tmp_path / "in"
    src.mkdir()
    big = trimesh.creation.icosphere(2)
    trimesh.Trimesh(big.vertices * 5.0, big.faces).export(src / "Wuson.off")
    trimesh.creation.box().export(src / "Wuson.ply")
    out = tmp_path / "out"
    r = _cli("generate", str(src), "-o", str(out), "--weights", weights, "--max-vertices", "12", "--json")
    recs = [json.loads(line) for line in r.stdout.splitlines()]
    assert sorted(Path(x["output"]).name for x in recs) == ["Wuson.off.glb", "Wuson.ply.glb"]
    sizes = [np.ptp(trimesh.load(out / n, force="mesh").vertices, axis=0).max() for n in ("Wuson.off.glb",
                                                                                           "Wuson.ply.glb")]
    assert sizes[0] > 3 * sizes[1]  # each result in its own input's frame: the radius-5 sphere and the unit box


def test_cli_generate_missing_input_is_clear(tmp_path):
    r = _cli("generate", str(tmp_path / "nope.ply"), "-o", str(tmp_path / "x.glb"), check=False)
    assert r.returncode == 2 and "no such file" in r.stderr and "Traceback" not in r.stderr


def test_shipped_weights_smoke(tmp_path):
    """The default weights load and turn a validation-style point cloud into a GLB."""
    root = default_weights_dir()
    assert (root / "vertex" / "model.safetensors").exists(), f"shipped weights missing in {root}"
    pipe = Pipeline.from_pretrained()
    m = trimesh.creation.box(extents=(1.0, 0.6, 0.4))
    shape = Shape(vertices=np.asarray(m.vertices) + 5, faces=np.asarray(m.faces))
    pts, nrm = sample_surface(shape, 4096, seed=0)
    cloud = Shape(vertices=pts.astype(np.float64), normals=nrm.astype(np.float64))
    res = pipe.generate(cloud, GenerateParams(seed=0, max_vertices=200))
    glb = res.export("glb")
    back = load_shape(glb, "result.glb")
    assert len(back.faces) > 0
    assert trimesh.load(io.BytesIO(glb), file_type="glb") is not None
