"""The pieces that let a warped board stand out of a wall (``tests/test_open_sheets.py::warped_ledge`` runs them
together through the pipeline): a sheet folded where it ends on a wall is set apart from the wall as one sheet
(``detach.detached``), and a corner placed where the points stop meets the corner of the same two planes
(``arrangement.snapped``)."""

from __future__ import annotations

import numpy as np
from test_open_sheets import _facing

from fastmesh.faces.meshops import edge_face_counts
from fastmesh.shapes.arrangement import snapped
from fastmesh.shapes.detach import detached


def _wall_and_warped_board() -> tuple[np.ndarray, np.ndarray]:
    """A wall (x = 0) whose triangulation runs an edge where a board ends on it (vertices 4-5, three faces there),
    and the board: two triangles folded 3 degrees along 4-6.  Vertices, then faces: the wall's six, the board's
    two."""
    v = np.array([[0, 0, 0], [0, 0, 1], [0, 1, 1], [0, 1, 0],  # the wall's corners W0-W3
                  [0, 0.5, 0.3], [0, 0.5, 0.7], [0.4, 0.5, 0.7], [0.4, 0.5 + 0.4 * np.tan(np.radians(3)), 0.3]])
    wall = np.array([[0, 1, 5], [0, 5, 4], [4, 5, 2], [4, 2, 3], [0, 4, 3], [1, 2, 5]])
    board = np.array([[4, 5, 6], [4, 6, 7]])
    faces = np.vstack([wall, board])
    return v, _facing(v, faces, np.r_[np.tile([1.0, 0, 0], (6, 1)), np.tile([0, 1.0, 0], (2, 1))])


def test_a_board_folded_where_it_ends_on_a_wall_is_set_apart_as_one_sheet():
    v, f = _wall_and_warped_board()
    assert edge_face_counts(f).max() == 3
    out_v, out_f = detached(v, f, 1e-6, 0.1)
    assert edge_face_counts(out_f).max() <= 2
    wall, board = out_f[:6], out_f[6:]  # (faces keep their order)
    assert not set(wall.ravel()) & set(board.ravel())  # the board shares no vertex with the wall
    shared = set(board[0]) & set(board[1])
    assert len(shared) == 2  # its fold is still one edge of its two halves
    assert np.allclose(np.sort(out_v[list(shared)], axis=0), np.sort(v[[4, 6]], axis=0))


def test_a_placed_corner_meets_the_corner_of_the_same_two_planes():
    corners = np.array([[0.0, 0, 0], [0.1, 0, 0],  # on planes 0 and 1: a's third plane placed (5), b's real (2)
                        [1.0, 0, 0], [1.1, 0, 0],  # on planes 3 and 4: both thirds placed (6, 7)
                        [2.0, 0, 0], [2.1, 0, 0]])  # two real corners
    meets = np.array([[0, 1, 5], [1, 0, 2], [3, 4, 6], [4, 3, 7], [8, 9, 2], [9, 8, 3]])
    out = snapped(corners, meets, 5, 0.2)
    assert np.allclose(out[0], corners[1]) and np.allclose(out[1], corners[1])  # onto the surer corner
    assert np.allclose(out[2], [1.05, 0, 0]) and np.allclose(out[3], [1.05, 0, 0])  # to their middle
    assert np.allclose(out[4:], corners[4:])  # no placed line: the planes' own corners stay
    assert np.allclose(snapped(corners, meets, 5, 0.05), corners)  # farther apart than the radius
    assert np.allclose(snapped(corners, meets, 10, 0.2), corners)  # nothing placed (a closed rebuild)
