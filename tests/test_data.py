"""Dataset cache: building from corpus files and folders, grouping, deterministic splits."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
import trimesh
from testdata import TEST_CORPUS, manifest

from fastmesh.shapes.io import load_shape
from fastmesh.shapes.shape import Normalization
from fastmesh.tokenizer import quantize_mesh
from fastmesh.training.data import build_dataset, dataset_stats, in_validation, load_dataset

# The committed base meshes with animation poses (a pose shares its base's group).
POSED = sorted({r["group"] for r in manifest() if r["kind"] == "pose"})


@pytest.fixture(scope="module")
def mini_corpus(tmp_path_factory) -> Path:
    """A corpus-shaped folder: 2 posed groups (base + 4 poses each), 6 plain small meshes, and a manifest."""
    root = tmp_path_factory.mktemp("mini") / "corpus"
    shutil.copytree(TEST_CORPUS, root)
    return root


def test_build_from_corpus_folder(mini_corpus, tmp_path):
    out = tmp_path / "cache.npz"
    stats = build_dataset([str(mini_corpus)], out, max_vertices=1000, val_fraction=0.5, workers=1)
    ds = load_dataset(out)
    n_files = len(list(mini_corpus.rglob("*.ply")))
    assert stats["meshes"] == len(ds) == n_files
    assert len(POSED) == 2 and stats["groups"] == 2 + 6
    groups = ds.arrays["group"]
    split = ds.arrays["split"]
    # Poses are never split from their base: one split per group.
    for g in np.unique(groups):
        assert len(np.unique(split[groups == g])) == 1
    assert sum(len(ds.indices(s)) for s in ("train", "val")) == len(ds) == len(ds.indices("all"))
    for i in range(len(ds)):
        assert bool(split[i]) == in_validation(str(groups[i]), 0.5)
    # Posed groups hold the base and its poses together.
    sizes = {g: int((groups == g).sum()) for g in np.unique(groups)}
    assert sorted(sizes.values())[-3:] == [1, 5, 5]


def test_split_is_deterministic(mini_corpus, tmp_path):
    a = build_dataset([str(mini_corpus)], tmp_path / "a.npz", val_fraction=0.3, workers=1)
    b = build_dataset([str(mini_corpus)], tmp_path / "b.npz", val_fraction=0.3, workers=1)
    assert a == b
    da, db = load_dataset(tmp_path / "a.npz"), load_dataset(tmp_path / "b.npz")
    assert np.array_equal(da.arrays["split"], db.arrays["split"]) and np.array_equal(da.arrays["q"], db.arrays["q"])
    assert in_validation("x/y.ply", 0.3) == in_validation("x/y.ply", 0.3)
    assert not in_validation("anything", 0.0)


def test_records_match_quantised_meshes(mini_corpus, tmp_path):
    out = tmp_path / "c.npz"
    build_dataset([str(mini_corpus)], out, workers=1)
    ds = load_dataset(out)
    for i in range(len(ds)):
        r = ds[i]
        shape = load_shape(mini_corpus / r.name)
        v = Normalization.fit(shape.vertices).apply(shape.vertices)
        q, f, cont = quantize_mesh(v, shape.faces)
        assert np.array_equal(r.q, q) and np.array_equal(r.faces, f)
        assert np.abs(r.residual).max() <= 0.5 + 1e-3
        assert np.allclose(r.continuous, cont, atol=1e-4)  # residuals stored as float16 cells


def test_build_from_files_and_tmp_folder(tmp_path):
    src = tmp_path / "meshes"
    src.mkdir()
    box = trimesh.creation.box()
    (src / "box.obj").write_text(box.export(file_type="obj"))
    (src / "box_copy.obj").write_text(box.export(file_type="obj"))  # exact duplicate
    (src / "sphere.ply").write_bytes(trimesh.creation.icosphere(subdivisions=3).export(file_type="ply"))  # 642 v
    (src / "cloud.xyz").write_text("0 0 0\n1 0 0\n0 1 0\n0 0 1\n")  # not a mesh format: not picked up
    (src / "broken.stl").write_bytes(b"solid x\nfacet garbage\n")
    stats = build_dataset([str(src)], tmp_path / "d.npz", max_vertices=100, workers=1)
    assert stats["meshes"] == 1
    dropped = stats["dropped"]
    assert dropped["duplicate"] == 1 and dropped["too_many_vertices"] == 1
    assert sum(dropped.values()) == 3  # + the broken STL (trimesh reads it as empty)
    ds = load_dataset(tmp_path / "d.npz")
    assert ds[0].name == "box.obj" and len(ds[0].q) == 8
    files = [str(TEST_CORPUS / p) for p in POSED]
    stats = build_dataset(files, tmp_path / "e.npz", workers=1)
    assert stats["meshes"] == 2 and stats["groups"] == 2
    assert set(dataset_stats(load_dataset(tmp_path / "e.npz"))) >= {"vertices", "faces", "fastmesh_tokens", "train"}


def test_build_errors(tmp_path):
    with pytest.raises(FileNotFoundError):
        build_dataset([str(tmp_path / "nope")], tmp_path / "x.npz")
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError):
        build_dataset([str(tmp_path / "empty")], tmp_path / "x.npz")


def test_split_by_package_holds_out_whole_packages(mini_corpus, tmp_path):
    out = tmp_path / "p.npz"
    stats = build_dataset([str(mini_corpus)], out, val_packages=("megaglest-data",), workers=1)
    ds = load_dataset(out)
    package = ds.arrays["package"]
    assert set(package) == {"ufoai-data", "megaglest-data"}
    # Every megaglest mesh and pose (the poses live in megaglest-data-poses/) is in validation, nothing else.
    assert np.array_equal(ds.arrays["split"] == 1, package == "megaglest-data")
    assert stats["val_packages"] == {"megaglest-data": int((package == "megaglest-data").sum())}
    assert ds[int(ds.indices("val")[0])].package == "megaglest-data"
    with pytest.raises(ValueError, match="no-such-package"):
        build_dataset([str(mini_corpus)], tmp_path / "x.npz", val_packages=("no-such-package",), workers=1)


def test_cli_default_holds_out_the_validation_packages_present(mini_corpus, tmp_path, capsys):
    from fastmesh.cli import main
    from fastmesh.training.data import VAL_PACKAGES

    assert not set(VAL_PACKAGES) & {"ufoai-data", "megaglest-data"}  # none present: a split by group
    assert main(["data", "build", str(mini_corpus), "-o", str(tmp_path / "a.npz"), "--workers", "1"]) == 0
    assert load_dataset(tmp_path / "a.npz").meta["val_packages"] == []
    assert main(["data", "build", str(mini_corpus), "-o", str(tmp_path / "b.npz"), "--workers", "1",
                 "--val-packages", "megaglest-data"]) == 0
    ds = load_dataset(tmp_path / "b.npz")
    assert np.array_equal(ds.arrays["split"] == 1, ds.arrays["package"] == "megaglest-data")
    assert main(["data", "build", str(mini_corpus), "-o", str(tmp_path / "c.npz"), "--workers", "1",
                 "--val-packages", "megaglest-data,nope"]) == 2
