"""An open input's solid with the caps over its openings taken off: the result stays open where its input is.

The face stage cuts an open input's solid as a closed input's (``solid.solid_mesh``): where the input is open (a
prop without its floor, a body part open at the waist, a tube's mouth), the cut closes the solid with faces that no
sample of the input carries, often sunk into the shape (a floor caved in, far from anything the artist made).  A
face across an opening lies far from every sample, where the input's generalized winding number reads neither
inside nor outside (about a half: the input wraps only part of the way around it), unlike a face that bridges a
concavity (outside, about 0) or closes a cavity (inside, about 1), which stay.  Such faces, with the faces joined to
them that lie nearly as far and read alike, are taken off; the rest keeps its winding.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from .meshops import piece_labels, remove_unreferenced
from .support import support_limit
from .winding import winding_numbers

# A face is across an opening where each of its SAMPLE_WEIGHTS points lies farther than this many support limits
# (``support.support_limit``) from the input's samples: beyond what a face on the surface strays between them.
SEED_LIMITS = 2.0
# Faces joined to one across an opening, through edges, go with it where their centroid lies farther than this.
GROW_LIMITS = 1.5
# ... and the input's winding number at their centroid, without its sign, lies within this of a half.
OPEN_BAND = 0.4
# The centroid and a point near each corner (barycentric weights, rows summing to 1).
SAMPLE_WEIGHTS = np.array([[2, 2, 2], [4, 1, 1], [1, 4, 1], [1, 1, 4]], dtype=np.float64) / 6.0


def across_openings(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray, normals: np.ndarray,
                    seed: int = 0) -> np.ndarray:
    """(F,) bool, the ``faces`` (F, 3) of ``vertices`` (N, 3) that lie across an opening of the input.

    Parameters
    ----------
    vertices : (N, 3) float
    faces : (F, 3) int, a surface wound either way
    points, normals : (P, 3) float, the input's samples, normals unit (outward or all inward: the winding number
        is read without its sign)
    seed : int, of the winding number's far-field subset
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    pts = np.asarray(points, dtype=np.float64)
    if not len(f) or len(pts) < 2:
        return np.zeros(len(f), dtype=bool)
    tree = cKDTree(pts)
    limit = support_limit(pts, 0.0, tree)
    samples = np.einsum("lc,fcd->fld", SAMPLE_WEIGHTS, v[f])
    far = tree.query(samples.reshape(-1, 3))[0].reshape(len(f), -1)
    may = far[:, 0] > GROW_LIMITS * limit
    if not (may & (far.min(1) > SEED_LIMITS * limit)).any():
        return np.zeros(len(f), dtype=bool)
    wound = np.abs(winding_numbers(samples[may, 0], pts, normals, seed))
    may[may] = np.abs(wound - 0.5) < OPEN_BAND
    seeds = may & (far.min(1) > SEED_LIMITS * limit)
    return _joined(f, may, seeds)


def _joined(faces: np.ndarray, may: np.ndarray, seeds: np.ndarray) -> np.ndarray:
    """(F,) bool, the faces of ``may`` (F,) joined through edges, among ``may`` only, to one of ``seeds`` (F,)."""
    label = piece_labels(faces[may])
    out = np.zeros(len(faces), dtype=bool)
    out[may] = np.isin(label, label[seeds[may]])
    return out


def uncapped(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray, normals: np.ndarray, seed: int = 0
             ) -> tuple[np.ndarray, np.ndarray, int]:
    """The surface without the faces that lie across the input's openings (:func:`across_openings`), its unused
    vertices dropped; and how many faces were taken off (0: the surface as it was)."""
    off = across_openings(vertices, faces, points, normals, seed)
    if not off.any() or off.all():
        return vertices, faces, 0
    v, f, _ = remove_unreferenced(vertices, np.asarray(faces)[~off])
    return v, f, int(off.sum())
