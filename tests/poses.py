"""Random poses for the tests' random families: any turn, millimetres to kilometres, far from the origin."""

from __future__ import annotations

import numpy as np
import trimesh


def random_pose(rng: np.random.Generator) -> tuple[np.ndarray, float, np.ndarray]:
    """A random turn (3, 3), a scale of 10^-3 to 10^3 (millimetres to kilometres) and a shift (3,) of up to 100
    sizes."""
    turn = trimesh.transformations.random_rotation_matrix(rng.random(3))[:3, :3]
    scale = 10 ** rng.uniform(-3, 3)
    return turn, scale, rng.uniform(-100, 100, 3) * scale


def posed(vertices: np.ndarray, pose: tuple[np.ndarray, float, np.ndarray]) -> np.ndarray:
    """(N, 3) ``vertices`` turned, scaled and shifted by ``pose`` (:func:`random_pose`)."""
    turn, scale, shift = pose
    return np.asarray(vertices, dtype=np.float64) @ turn.T * scale + shift


def turned(normals: np.ndarray, pose: tuple[np.ndarray, float, np.ndarray]) -> np.ndarray:
    """(N, 3) ``normals`` turned by ``pose`` (neither scaled nor shifted)."""
    return np.asarray(normals, dtype=np.float64) @ pose[0].T
