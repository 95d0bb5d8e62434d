"""The shipped pipeline gives the recorded tokens and meshes on fixed seeds (``tests/data/golden.npz``).

Three inputs, each through ``Pipeline.steps`` with the shipped weights on the CPU: a point cloud (a torus's
samples), a mesh (a turned, stretched icosphere, brought to a face count) and a box (rebuilt from its planes,
no tokens).  Every vertex-token sequence the decoder returns is compared, then the mesh: faces exactly, vertices
to 1e-9 (float64 sums may round differently on another CPU; a different token changes far more).

A change that is meant to alter results rewrites the file: ``python tests/test_golden.py`` (and says why in its
commit).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh

from fastmesh.batch import decode
from fastmesh.evaluation.primitives import box, torus
from fastmesh.params import GenerateParams
from fastmesh.pipeline import Pipeline
from fastmesh.shapes.io import sample_surface
from fastmesh.shapes.shape import Shape

GOLDEN = Path(__file__).parent / "data" / "golden.npz"


def _cloud() -> Shape:
    points, normals = sample_surface(torus(), 2048, seed=5)
    return Shape(vertices=points * 3.0 + [10.0, -2.0, 0.5], faces=None, normals=normals)


def _mesh() -> Shape:
    mesh = trimesh.creation.icosphere(3)
    mesh.apply_transform(trimesh.transformations.rotation_matrix(0.7, [1.0, 2.0, 0.5]))
    mesh.apply_scale([31.3, 20.1, 17.9])
    return Shape(vertices=np.asarray(mesh.vertices, dtype=np.float64), faces=np.asarray(mesh.faces, dtype=np.int64))


# name -> (input, parameters)
CASES = {
    "cloud": (_cloud, GenerateParams(seed=3, max_vertices=60)),
    "mesh": (_mesh, GenerateParams(seed=7, max_vertices=60, target_faces=80)),
    "box": (box, GenerateParams(seed=0)),
}


def run(pipe: Pipeline, shape: Shape, params: GenerateParams) -> tuple[list[np.ndarray], np.ndarray, np.ndarray]:
    """One generation driven step by step, as ``fastmesh.batch.Batch`` drives it.

    Returns
    -------
    tokens : list of (T,) int64, every sequence the decoder returned (BOS ... EOS), in order
    vertices : (V, 3) float64
    faces : (F, 3) int64
    """
    steps, tokens = pipe.steps(shape, params), []
    try:
        request = next(steps)
        while True:
            with pipe.threads_for("vertices"):
                got = decode(pipe.decoder, [request])[0]
            if isinstance(got, BaseException):
                raise got
            tokens += [t.cpu().numpy().astype(np.int64).ravel() for t in got]
            request = steps.send(got)
    except StopIteration as end:
        result = end.value
    return tokens, result.vertices, result.faces


def record() -> dict[str, np.ndarray]:
    """Every case's arrays, keyed ``<case>/tokens<i>``, ``<case>/vertices``, ``<case>/faces``."""
    pipe = Pipeline.from_pretrained(device="cpu")
    arrays = {}
    for name, (make, params) in CASES.items():
        tokens, vertices, faces = run(pipe, make(), params)
        arrays |= {f"{name}/tokens{i}": t for i, t in enumerate(tokens)}
        arrays |= {f"{name}/vertices": vertices, f"{name}/faces": faces}
    return arrays


@pytest.fixture(scope="module")
def shipped():
    torch.manual_seed(0)
    return Pipeline.from_pretrained(device="cpu")


@pytest.mark.parametrize("name", list(CASES))
def test_same_tokens_and_mesh_as_recorded(shipped, name):
    golden = np.load(GOLDEN)
    make, params = CASES[name]
    tokens, vertices, faces = run(shipped, make(), params)
    want = sorted((k for k in golden.files if k.startswith(f"{name}/tokens")), key=lambda k: int(k[len(name) + 7:]))
    assert len(tokens) == len(want), f"{len(tokens)} token sequences, {len(want)} recorded"
    for got, key in zip(tokens, want, strict=True):
        assert np.array_equal(got, golden[key]), f"{key} differs"
    assert np.array_equal(faces, golden[f"{name}/faces"])
    assert vertices.shape == golden[f"{name}/vertices"].shape
    assert np.allclose(vertices, golden[f"{name}/vertices"], rtol=0, atol=1e-9)


if __name__ == "__main__":
    np.savez_compressed(GOLDEN, **record())
    print(f"wrote {GOLDEN}", file=sys.stderr)
