"""Progress goes one way: the fraction never decreases, the stage never returns to one passed, and a stage
that does not run is never named (filtering once showed 100 % with filtering off, and the stages went
faces -> enhancer -> faces as the candidates took turns)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from fastmesh.pipeline import GenerateParams, Pipeline
from fastmesh.progress import STAGES, Progress
from fastmesh.shapes.shape import Shape

ORDER = [name for name, _, _ in STAGES]


@pytest.fixture(scope="module")
def pipe():
    return Pipeline.random("tiny", seed=0)


def _turned_box_and_ball() -> Shape:
    """Not a polyhedron (the ball), with walls at an angle (the box): made in two frames by the networks."""
    box = trimesh.creation.box(extents=(2.0, 1.0, 0.6))
    ball = trimesh.creation.icosphere(2, radius=0.45)
    ball.apply_translation([1.0, 0.0, 0.3])
    both = trimesh.util.concatenate([box, ball])
    both.apply_transform(trimesh.transformations.rotation_matrix(0.5, [0.3, 1.0, 0.2]))
    return Shape(vertices=np.asarray(both.vertices), faces=np.asarray(both.faces))


def _sphere() -> Shape:
    m = trimesh.creation.icosphere(3)
    return Shape(vertices=np.asarray(m.vertices) * [3.0, 2.0, 1.2], faces=np.asarray(m.faces))


def _one_way(seen: list[tuple[str, float]], filtering: bool) -> None:
    fractions = [f for _, f in seen]
    assert fractions == sorted(fractions) and fractions[-1] == 1.0 and 0.0 <= fractions[0], seen
    ranks = [ORDER.index(s) for s, _ in seen]
    assert ranks == sorted(ranks), seen
    named = {s for s, _ in seen}
    assert named == ({"encode", "vertices", "enhancer", "faces"} | ({"filtering"} if filtering else set())), named


@pytest.mark.parametrize("filtering", [False, True])
@pytest.mark.parametrize("candidates", [1, 3])
@pytest.mark.parametrize("make", [_sphere, _turned_box_and_ball], ids=["one-frame", "two-frames"])
def test_progress_goes_one_way_over_candidates_and_frames(pipe, make, candidates, filtering):
    seen = []
    res = pipe.generate(make(), GenerateParams(seed=2, max_vertices=24, candidates=candidates, filtering=filtering),
                        progress=lambda stage, fraction: seen.append((stage, fraction)))
    _one_way(seen, filtering)
    assert res.info["candidates"] == candidates
    if make is _turned_box_and_ball:
        assert seen.count(("encode", 0.015)) == 1  # the second frame's encoding, half-way through the stage


def test_a_shape_rebuilt_from_its_planes_reports_faces_only(pipe):
    seen = []
    box = trimesh.creation.box()
    res = pipe.generate(Shape(vertices=np.asarray(box.vertices), faces=np.asarray(box.faces)), GenerateParams(),
                        progress=lambda stage, fraction: seen.append((stage, fraction)))
    assert res.info["result_from"] in ("planes", "input") and seen == [("faces", 1.0)]


def test_progress_spans_without_and_with_filtering():
    got = []
    p = Progress(lambda stage, fraction: got.append((stage, round(fraction, 6))), filtering=False)
    p("encode")
    p("vertices", 0.5)
    p("enhancer", 0.0, 1, 2)
    p("faces", 0.0, 1, 2)
    p("faces", 1.0, 1, 2)
    assert got == [("encode", 0.0), ("vertices", 0.415), ("enhancer", 0.815), ("faces", 0.915), ("faces", 1.0)]
    with pytest.raises(ValueError):
        p("filtering", 0.5)  # not a stage of this run

    got.clear()
    p = Progress(lambda stage, fraction: got.append((stage, round(fraction, 6))), filtering=True)
    p("faces", 0.0, 0, 2)      # candidate 1: faces, then filtering, in the first half of their joint span
    p("filtering", 1.0, 0, 2)
    p("faces", 0.0, 1, 2)      # candidate 2's face pass: still shown as filtering, never back to faces
    p("filtering", 0.5, 1, 2)
    p("vertices", 0.1)         # a report out of order changes neither the stage nor the fraction
    p.done()
    assert got == [("faces", 0.83), ("filtering", 0.915), ("filtering", 0.915), ("filtering", 0.975),
                   ("filtering", 0.975), ("filtering", 1.0)]
