"""Surface face selection: restricted Delaunay candidates, manifold selection, hole filling, the ladder
of simple shapes, and the eval verbs that score it side by side."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from fastmesh.cli import main
from fastmesh.evaluation.metrics import mesh_topology
from fastmesh.faces import holes, mesh_from_adjacency
from fastmesh.faces import surface_triangles as sf
from fastmesh.faces.selection import Selection
from fastmesh.faces.support import SupportCache, support_distance, support_limit
from fastmesh.faces.triangles import TriangleConfig
from fastmesh.shapes.shape import Normalization
from fastmesh.tokenizer import dequantize, quantize_mesh

PRIMITIVES = {
    "box": lambda: trimesh.creation.box(),
    "cylinder": lambda: trimesh.creation.cylinder(radius=0.5, height=1.0, sections=16),
    "cone": lambda: trimesh.creation.cone(radius=0.5, height=1.0, sections=16),
    "icosphere1": lambda: trimesh.creation.icosphere(subdivisions=1),
    "icosphere2": lambda: trimesh.creation.icosphere(subdivisions=2),
}
SURFACE = TriangleConfig(remove_unreferenced=False)


def _max_faces_per_edge(faces: np.ndarray) -> int:
    f = np.asarray(faces)
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    return int(np.unique(e, axis=0, return_counts=True)[1].max())


def _primitive(name: str, normals: bool = False):
    """The primitive's vertices (merged) and 8192 samples of its surface (and their normals)."""
    m = PRIMITIVES[name]()
    m.merge_vertices()
    pts, fi = trimesh.sample.sample_surface(m, 8192, seed=0)
    return (m, np.asarray(pts), m.face_normals[fi]) if normals else (m, np.asarray(pts))


def _assert_closed_on_surface(m, v, f, pts):
    top = mesh_topology(v, f)
    assert top["watertight"] and top["pieces"] == 1, top
    assert _max_faces_per_edge(f) == 2
    assert (support_distance(v, f, pts) <= support_limit(pts, 0.0)).all()  # no face off the surface
    # oriented outward; 7-bit cells move the vertices a little
    assert trimesh.Trimesh(v, f, process=False).volume == pytest.approx(m.volume, rel=0.05)


@pytest.mark.parametrize("name", list(PRIMITIVES))
def test_primitives_close_without_a_model(name):
    m, pts = _primitive(name)
    v, f = mesh_from_adjacency(m.vertices, np.zeros((0, 2), dtype=np.int64), SURFACE, points=pts)
    _assert_closed_on_surface(m, v, f, pts)
    if name == "box":
        assert len(f) == 12


def test_restricted_delaunay_anchor_on_the_box():
    m, pts = _primitive("box")
    f = sf.restricted_delaunay_mesh(m.vertices, pts)
    assert len(f) == 12 and mesh_topology(m.vertices, f)["watertight"]


@pytest.fixture(scope="module")
def shipped():
    from fastmesh.pipeline import Pipeline

    return Pipeline.from_pretrained(device="cpu")


@pytest.mark.parametrize("name", ["box", "cylinder"])
def test_shipped_face_model_closes_box_and_cylinder(shipped, name):
    """The shipped face model's edges and logits on the primitive's own 7-bit vertices."""
    m, pts, nrm = _primitive(name, normals=True)
    norm = Normalization.fit(m.vertices)
    q, _, _ = quantize_mesh(norm.apply(m.vertices), m.faces)
    unit_pts = norm.apply(pts)
    n_fp = shipped.face.cfg.encoder.n_points
    edges, logits = shipped.face.predict_edges(q, unit_pts[:n_fp], nrm[:n_fp], filtering=shipped.filter_config,
                                               return_logits=True)
    cfg = replace(shipped.triangle_config, remove_unreferenced=False)
    v, f = mesh_from_adjacency(dequantize(q), edges, cfg, points=unit_pts, logits=logits)
    _assert_closed_on_surface(trimesh.Trimesh(norm.apply(m.vertices), m.faces), v, f, unit_pts)
    if name == "box":
        assert len(f) == 12


def test_selection_never_puts_an_edge_in_three_faces():
    # A book: five pages hinged on edge (0, 1), spread 72 degrees apart, all scored well.
    ang = np.arange(5) * 2 * np.pi / 5
    v = np.concatenate([[[0, 0, 0], [0, 0, 1.0]], np.stack([np.cos(ang), np.sin(ang), np.full(5, 0.5)], 1)])
    pages = np.array([[0, 1, 2 + k] for k in range(5)])
    frames = np.full((len(v), 2, 3), np.nan)
    f, _ = sf.select_faces(v, pages, np.ones(5), frames)
    assert len(f) == 2 and _max_faces_per_edge(f) == 2
    # Dense random candidates around a sphere: whatever is picked stays edge-manifold.
    rng = np.random.default_rng(0)
    s = rng.normal(size=(60, 3))
    s /= np.linalg.norm(s, axis=1, keepdims=True)
    close = np.argwhere(np.linalg.norm(s[:, None] - s[None], axis=2) < 0.9)
    pts = trimesh.sample.sample_surface(trimesh.creation.icosphere(4), 8192, seed=0)[0]
    f = sf.surface_mesh(s, close, pts, TriangleConfig(support_tol=0.1))[1]
    assert len(f) and _max_faces_per_edge(f) <= 2


def test_folded_faces_are_not_both_selected():
    # Both diagonal splits of a flat quad: the second pair folds onto the first.
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0.0]])
    cand = np.array([[0, 1, 2], [0, 2, 3], [0, 1, 3], [1, 2, 3]])
    f, _ = sf.select_faces(v, cand, np.array([4.0, 3, 2, 1]), np.full((4, 2, 3), np.nan))
    assert sorted(map(tuple, np.sort(f, 1).tolist())) == [(0, 1, 2), (0, 2, 3)]


def _book(vertices, frames, faces) -> Selection:
    """The selection's bookkeeping holding ``faces`` (fold angle 30 degrees)."""
    book = Selection(vertices, frames, 30.0)
    for t in np.asarray(faces).tolist():
        book.add(*t)
    return book


def test_fill_closes_a_hole_and_leaves_an_open_input_open():
    m, pts = _primitive("icosphere2")
    f = np.asarray(m.faces)[np.r_[0:5, 12:len(m.faces)]]  # a hole where 7 faces were
    book = _book(m.vertices, sf.vertex_frames(m.vertices, pts), f)
    filled = holes.fill_holes(m.vertices, f, book, pts, support_limit(pts, 0.0))
    assert mesh_topology(m.vertices, filled)["watertight"]
    # A flat open grid: its outer boundary is not a hole of the surface.
    k = 6
    x, y = np.meshgrid(np.arange(k), np.arange(k), indexing="ij")
    grid = np.stack([x.ravel(), y.ravel(), np.zeros(k * k)], 1) / (k - 1)
    plane = np.c_[np.random.default_rng(0).random((8192, 2)), np.zeros(8192)]
    f = sf.surface_mesh(grid, np.zeros((0, 2), dtype=np.int64), plane)[1]
    assert len(f) == 2 * (k - 1) ** 2 and not mesh_topology(grid, f)["watertight"]


def test_overlapping_faces_at_a_vertex_without_tangent_plane_are_not_both_selected():
    """At a crease or corner (no tangent plane: NaN frames) two nearly parallel faces around a shared
    vertex that cover the same angle there are a double layer; faces across the crease are not."""
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0.9, -0.1, 0.02], [0.5, 1.2, 0.01], [0, 0, 1.0], [0, 1, 1.0]])
    cand = np.array([[0, 1, 2], [0, 3, 4], [0, 5, 6]])  # the second overlaps the first; the third stands up
    f, _ = sf.select_faces(v, cand, np.array([3.0, 2, 1]), np.full((len(v), 2, 3), np.nan))
    assert sorted(map(tuple, np.sort(f, 1).tolist())) == [(0, 1, 2), (0, 5, 6)]


@pytest.mark.parametrize("seed, wrong", [(1, 6), (3, 6), (2, 6), (6, 10), (0, 16)])
def test_fill_replaces_wrong_faces_that_block_a_hole(seed, wrong):
    """A few wrong restricted-Delaunay triangles taken first leave holes no ear fits (they fold onto the
    ears or hold the edges the ears need); re-clipping without the faces along such a hole closes the
    sphere, and never puts an edge in three faces or leaves a vertex out.  In the last three cases the
    faces taken out include every face of some vertex: it must join the hole's boundary first."""
    m = trimesh.creation.icosphere(2, radius=0.45)
    pts = trimesh.sample.sample_surface(m, 8192, seed=0)[0]
    f, _, limit = sf.on_surface(m.vertices, sf.delaunay_triangles(m.vertices), pts)
    true = set(map(tuple, np.sort(m.faces, 1).tolist()))
    is_true = np.array([tuple(t) in true for t in f.tolist()])
    rng = np.random.default_rng(seed)
    score = np.where(is_true, 1.0, -1.0) + rng.uniform(0, 0.1, len(f))
    score[rng.choice(np.flatnonzero(~is_true), size=wrong, replace=False)] = 5.0
    sel, book = sf.select_faces(m.vertices, f, score, sf.vertex_frames(m.vertices, pts))
    assert len(holes.boundary_loops(sel)) > 0
    filled = holes.fill_holes(m.vertices, sf.orient_faces(m.vertices, sel), book, pts, limit)
    assert _max_faces_per_edge(filled) == 2 and len(np.unique(filled)) == len(m.vertices)
    assert mesh_topology(m.vertices, filled)["watertight"]


def test_boundary_loops_of_an_open_cylinder():
    m = trimesh.creation.cylinder(radius=1, height=1, sections=8)
    m.merge_vertices()
    side = m.faces[np.abs(m.face_normals[:, 2]) < 0.5]
    loops = holes.boundary_loops(side)
    assert sorted(len(x) for x in loops) == [8, 8]


def test_delaunay_triangles_of_flat_and_degenerate_inputs():
    flat = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [0.5, 0.5, 0]])
    assert len(sf.delaunay_triangles(flat)) == 4
    assert len(sf.delaunay_triangles(np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0.0]]))) == 0
    assert len(sf.delaunay_triangles(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0]]))) == 4


def _eval_folders(tmp_path: Path) -> tuple[Path, Path]:
    inputs, refs = tmp_path / "inputs", tmp_path / "reference"
    inputs.mkdir()
    refs.mkdir()
    for name, mesh in (("box", trimesh.creation.box((2, 1, 3))), ("ball", trimesh.creation.icosphere(1))):
        mesh.apply_translation([5, -1, 2])  # an off-centre frame, to check the saved results' frame
        pts, fi = trimesh.sample.sample_surface(mesh, 4096, seed=0)
        np.savez(inputs / f"{name}.npz", points=pts, normals=mesh.face_normals[fi])
        (refs / f"{name}.ply").write_bytes(mesh.export(file_type="ply"))
    return inputs, refs


def test_eval_gt_vertices_baseline_side_by_side_and_save(tmp_path, capsys, weights):
    inputs, refs = _eval_folders(tmp_path)
    save = tmp_path / "saved"
    code = main(["eval", "--inputs", str(inputs), "--reference", str(refs), "--gt-vertices", "--baseline",
                 "--save", str(save), "--weights", weights, "--json"])
    assert code == 0
    doc = json.loads(capsys.readouterr().out)
    summary = doc["summary"]
    assert {"fastmesh", "selection_cliques", "restricted_delaunay"} <= set(summary)
    anchor = summary["restricted_delaunay"]
    assert anchor["share_edge_manifold"] == 1.0 and anchor["watertight_references"] == 2
    for row in doc["meshes"]:
        assert {"cd", "hd", "edge_f1", "watertight", "seconds"} <= set(row["restricted_delaunay"])
    box = trimesh.load(save / "restricted_delaunay" / "box.ply", process=False)
    ref = trimesh.load(refs / "box.ply", process=False)
    assert np.allclose(box.bounds, ref.bounds, atol=0.05)  # the reference's frame, 7-bit vertices
    assert (save / "box.ply").exists() or doc["meshes"][0]["fastmesh"].get("failed")


def test_eval_end_to_end_save_and_topology(tmp_path, capsys, weights):
    inputs, refs = _eval_folders(tmp_path)
    save = tmp_path / "saved"
    code = main(["eval", "--inputs", str(inputs), "--reference", str(refs), "--limit", "1", "--save", str(save),
                 "--weights", weights, "--json", "--max-vertices", "16"])
    assert code == 0
    doc = json.loads(capsys.readouterr().out)
    row = doc["meshes"][0]
    if not row["fastmesh"].get("failed"):
        assert {"edge_manifold", "watertight", "pieces"} <= set(row["fastmesh"])
        assert (save / f"{row['name']}.ply").exists()
    assert "more_pieces_than_reference" in doc["summary"]["fastmesh"] or doc["summary"]["fastmesh"]["failures"]
    assert row["reference"]["watertight"] is True


def test_loops_found_from_seed_edges_equal_the_whole_walk_restricted_to_them():
    """The repair's local walk (from a hole's edges outward) finds the loops of ``boundary_loops`` that
    hold those edges' connected boundary, in the same order: here on a sphere with many holes."""
    m = trimesh.creation.icosphere(3)
    rng = np.random.default_rng(0)
    keep = np.ones(len(m.faces), bool)
    keep[rng.choice(len(m.faces), 120, replace=False)] = False
    f = np.asarray(m.faces)[keep]
    book = _book(m.vertices, np.full((len(m.vertices), 2, 3), np.nan), f)
    everything = holes.boundary_loops(f)
    assert len(everything) > 20 and any(len(x) > 3 for x in everything)
    edges = [holes._loop_edges(x) for x in everything]
    for i in (0, 5, len(everything) - 1):
        seeds = edges[i] | {(0, 1)}  # a seed that is no boundary edge is ignored
        local = holes._loops_through(book, seeds)
        touching = [x for x in everything if x in local]
        assert local == touching and everything[i] in local
        meets = [x for x in everything if holes._loop_edges(x) & seeds]
        assert [x for x in local if holes._loop_edges(x) & seeds] == meets
    assert holes._loops_through(book, set()) == []


def _sphere_with_hole(n_faces: int = 7):
    """Icosphere faces less those nearest one point (one hole), their bookkeeping, points, limit, hole loop."""
    m, pts = _primitive("icosphere2")
    order = np.argsort(np.linalg.norm(m.triangles_center - m.triangles_center[0], axis=1))
    f = np.asarray(m.faces)[np.sort(order[n_faces:])]
    book = _book(m.vertices, sf.vertex_frames(m.vertices, pts), f)
    (loop,) = holes.boundary_loops(f)
    return m, f, book, pts, support_limit(pts, 0.0), loop


def _all_triangulations(chain: list[int]):
    """Every triangulation of the polygon ``chain`` (closed by its first and last vertex): exhaustive."""
    if len(chain) < 3:
        yield []
        return
    for m in range(1, len(chain) - 1):
        for left in _all_triangulations(chain[: m + 1]):
            for right in _all_triangulations(chain[m:]):
                yield [(chain[0], chain[m], chain[-1]), *left, *right]


@pytest.mark.parametrize("taken_chord", [False, True])
def test_best_whole_triangulation_equals_the_cheapest_of_all_triangulations(taken_chord):
    """The dynamic programme against its slow twin: every triangulation of the hole enumerated, those
    with a face off the surface, not fitting the selection or adding an edge it has ruled out, the least
    total support distance kept.  With a face standing on one of the hole's chords, that chord is never used."""
    m, f, book, pts, limit, loop = _sphere_with_hole()
    v = np.asarray(m.vertices, dtype=np.float64)
    tree = cKDTree(pts)
    if taken_chord:  # a face on the chord (loop[0], loop[3]), standing far off the hole
        v = np.vstack([v, 3 * v[loop[0]]])
        frames = np.concatenate([sf.vertex_frames(m.vertices, pts), np.full((1, 2, 3), np.nan)])
        book = _book(v, frames, [*f.tolist(), (loop[0], loop[3], len(v) - 1)])
    chords = {tuple(sorted(e)) for e in holes._loop_edges(loop)}

    def allowed(t):
        new = [tuple(sorted(e)) for e in ((t[0], t[1]), (t[1], t[2]), (t[0], t[2]))]
        return (support_distance(v, np.array([t]), pts, tree)[0] <= limit and book.fits(*t)
                and not any(e not in chords and book.third.get(e) for e in new))

    costs = [sum(support_distance(v, np.array(tr), pts, tree)) for tr in _all_triangulations(loop)
             if all(allowed(t) for t in tr)]
    got = holes._best_triangulation(loop, book, SupportCache(v, pts, tree), limit)
    assert got is not None and len(got) == len(loop) - 2
    assert sum(support_distance(v, np.array(got), pts, tree)) == pytest.approx(min(costs), abs=1e-9)
    assert all(tuple(sorted(t)) in {tuple(sorted(x)) for x in book.face_normals} for t in got)
    if taken_chord:
        assert not any({loop[0], loop[3]} <= set(t) for t in got)


def test_best_whole_triangulation_skips_triangles_the_selection_refuses(monkeypatch):
    """The programme checks the selection only on the faces of its cheapest triangulation and looks again
    without those refused: against every triangulation enumerated, with the selection refusing a face of
    the unrestricted optimum, and then a face of the next one too."""
    m, f, book, pts, limit, loop = _sphere_with_hole(12)
    v = np.asarray(m.vertices, dtype=np.float64)
    support = SupportCache(v, pts)
    fits = book.fits
    chords = {tuple(sorted(e)) for e in holes._loop_edges(loop)}
    everything = list(_all_triangulations(loop))
    assert len(loop) >= 6 and len(everything) > 40

    def allowed(t):
        new = [tuple(sorted(e)) for e in ((t[0], t[1]), (t[1], t[2]), (t[0], t[2]))]
        return (support(np.array([t]))[0] <= limit and book.fits(*t)
                and not any(e not in chords and book.third.get(e) for e in new))

    def cheapest():
        costs = [(sum(support(np.array(tr))), tr) for tr in everything if all(allowed(t) for t in tr)]
        return min(costs, key=lambda c: c[0])

    refused, asked = set(), []

    def picky(a, b, c):
        asked.append((a, b, c))
        return frozenset((a, b, c)) not in refused and fits(a, b, c)

    monkeypatch.setattr(book, "fits", picky)
    for _ in range(2):  # refuse a face of the optimum, then one of the optimum without it
        refused.add(frozenset(cheapest()[1][0]))
    want = cheapest()[0]
    asked.clear()
    got = holes._best_triangulation(loop, book, support, limit)
    assert got is not None and len(got) == len(loop) - 2
    assert sum(support(np.array(got))) == pytest.approx(want, abs=1e-12)
    assert {frozenset(t) for t in asked} >= refused  # it did meet the refused faces on its way


def test_selection_keeps_its_boundary_while_faces_come_and_go():
    """``open`` (each vertex's neighbours across an edge of one face) against the edges ``third`` holds
    in exactly one face, after a shuffled run of additions and removals."""
    m, pts = _primitive("icosphere2")
    book = Selection(m.vertices, np.full((len(m.vertices), 2, 3), np.nan), 30.0)
    rng = np.random.default_rng(1)
    faces = np.asarray(m.faces).tolist()
    present = []
    for step in range(600):
        if present and (rng.random() < 0.4 or len(present) == len(faces)):
            book.remove(*present.pop(rng.integers(len(present))))
        else:
            t = faces[rng.integers(len(faces))]
            if t not in present:
                book.add(*t)
                present.append(t)
        if step % 50 == 0 or step == 599:
            want = {e for e, z in book.third.items() if len(z) == 1}
            have = {(x, y) for x, ys in book.open.items() for y in ys if x < y}
            assert have == want and all(x in book.open[y] for x, ys in book.open.items() for y in ys)
    assert len(want) > 20


def test_a_hole_ear_clipping_leaves_is_closed_by_the_whole_triangulation(monkeypatch):
    """With ear clipping stuck on every loop, holes up to ``WHOLE_LOOP_MAX`` edges still close; above it
    they stay open (and nothing else changes)."""
    m, f, book, pts, limit, loop = _sphere_with_hole()
    monkeypatch.setattr(holes, "_clip_loop", lambda *args: None)
    filled = holes.fill_holes(m.vertices, f, book, pts, limit)
    assert mesh_topology(m.vertices, filled)["watertight"] and _max_faces_per_edge(filled) == 2
    m, f, book, pts, limit, loop = _sphere_with_hole()
    monkeypatch.setattr(holes, "WHOLE_LOOP_MAX", len(loop) - 1)
    assert len(holes.fill_holes(m.vertices, f, book, pts, limit)) == len(f)
