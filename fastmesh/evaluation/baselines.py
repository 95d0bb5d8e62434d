"""The baselines an evaluation sets beside our results (:mod:`.eval`): the convex hull, screened Poisson with
quadric decimation, quadric decimation of a mesh input; and a dense remesh of a reference, an input without the
artist's structure."""

from __future__ import annotations

import numpy as np

from ..faces.decimation import quadric_decimation
from ..shapes.io import sample_surface
from ..shapes.shape import Shape, ShapeError


def convex_hull(shape: Shape) -> tuple[np.ndarray, np.ndarray]:
    import trimesh

    hull = trimesh.PointCloud(shape.vertices).convex_hull
    return np.asarray(hull.vertices), np.asarray(hull.faces)


def poisson(shape: Shape, target_faces: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Screened Poisson (depth 8) on 8192 oriented samples, then quadric decimation to ``target_faces``."""
    import pymeshlab

    pts, nrm = sample_surface(shape, 8192, seed=seed)
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=pts.astype(np.float64), v_normals_matrix=nrm.astype(np.float64)))
    ms.generate_surface_reconstruction_screened_poisson(depth=8, preclean=True)
    ms.meshing_decimation_quadric_edge_collapse(targetfacenum=max(4, int(target_faces)), preservenormal=True)
    m = ms.current_mesh()
    return np.asarray(m.vertex_matrix()), np.asarray(m.face_matrix())


def decimation(shape: Shape, target_faces: int) -> tuple[np.ndarray, np.ndarray]:
    """Quadric edge-collapse decimation of a mesh input to about ``target_faces``
    (``decimation.quadric_decimation``): what a user does with a dense mesh instead of retopology."""
    if shape.faces is None:
        raise ShapeError("not_a_mesh", "decimation needs a mesh input")
    return quadric_decimation(shape.vertices, shape.faces, target_faces)


def dense_remesh(vertices: np.ndarray, faces: np.ndarray, target_faces: int = 20_000, seed: int = 0
                 ) -> tuple[np.ndarray, np.ndarray]:
    """A dense mesh of the same surface without the artist's structure: isotropic remeshing (pymeshlab) to
    edges of the length that gives about ``target_faces`` equilateral faces, as a scan or a sculpt would
    be.  Creases of over 30 degrees keep a line of vertices; corners and the artist's vertices do not."""
    import pymeshlab

    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    area = 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1).sum()
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=v, face_matrix=f.astype(np.int32)))
    ms.meshing_merge_close_vertices()
    ms.meshing_isotropic_explicit_remeshing(iterations=4, targetlen=pymeshlab.PureValue(
        float(np.sqrt(4.0 * area / (np.sqrt(3.0) * target_faces)))))
    m = ms.current_mesh()
    return np.asarray(m.vertex_matrix()), np.asarray(m.face_matrix())
