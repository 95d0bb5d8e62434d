"""BPT whole-mesh tokenizer: patchified aggregation with block-wise indexing (Weng et al. 2024).

Written from the paper and a reading of the authors' serialiser; the code is ours.

Patches.  Faces are visited in canonical order (``vanilla.canonical_mesh``).  The first
face not yet emitted picks the *centre*: its vertex with the most not-yet-emitted incident
faces (the authors track remaining edges instead; both favour vertices with big fans).
The centre's remaining faces, each seen as the edge opposite the centre, are walked into
one chain ``v0 v1 ... vk`` (a fan: faces ``(c, v_j, v_j+1)``); faces that do
not fit the chain stay for later patches.  A patch emits the centre once, marked, then the
chain.

Tokens.  A cell is ``16 * block + offset`` per axis (as in ``tokenizer.vertex``): block id
``bx*64 + by*8 + bz``, offset id ``ox*256 + oy*16 + oz``.  The centre is always written as a
*patch block* token (its block, marked as a patch start) and its offset; every chain vertex
writes a plain block token only when its block differs from the previous vertex's, then its
offset:

    BOS  P(b_c) O(c) O(v0) B(b) O(v1) O(v2) ...  P(b_c') O(c') ...  EOS

Vocabulary (5123 ids): 0 PAD, 1 BOS, 2 EOS, 3..514 blocks, 515..4610 offsets,
4611..5122 patch blocks.

Winding.  With ``oriented=True`` (default) the chain follows the faces' directed edges, so
decoding returns every face with its winding (exact round trip of the canonical mesh); a
face whose orientation disagrees with its neighbours ends the chain and starts another
patch.  ``oriented=False`` walks undirected edges like the authors' serialiser (chains can
be longer on inconsistently oriented meshes) and only the winding of each fan's first face
is kept; the face *set* still round-trips.

Compared with the authors' serialiser (which always writes a block token for the first
chain vertex, since a patch block never equals a plain block), the rule above saves up to
one token per patch; ``first_block_explicit=True`` reproduces the authors' count.
"""

from __future__ import annotations

import numpy as np

from .grid import N_BLOCKS, N_OFFSETS, cells_from_keys, split_cells
from .vanilla import canonical_mesh, mesh_from_soup

PAD, BOS, EOS = 0, 1, 2
N_SPECIAL = 3
BLOCK0 = N_SPECIAL
OFFSET0 = BLOCK0 + N_BLOCKS
PATCH0 = OFFSET0 + N_OFFSETS
VOCAB_SIZE = PATCH0 + N_BLOCKS  # 5123


def patchify(faces: np.ndarray, n_vertices: int, oriented: bool = True) -> tuple[list[int], list[int]]:
    """Group faces into fans around centre vertices.

    Parameters
    ----------
    faces : (F, 3) int64
        Canonical faces (see ``vanilla.canonical_mesh``).
    n_vertices : int
    oriented : bool
        Follow directed edges (winding-exact) or undirected ones (authors' variant).

    Returns
    -------
    seq : list of int
        Vertex indices, patch after patch: centre, then chain.
    starts : list of int
        Position in ``seq`` of each patch's centre.
    """
    n_faces = len(faces)
    if n_faces == 0:
        return [], []
    flat = faces.ravel()
    by_vertex = np.argsort(flat, kind="stable")
    inc = (by_vertex // 3).tolist()  # incident faces, grouped by vertex
    bounds = np.searchsorted(flat[by_vertex], np.arange(n_vertices + 1)).tolist()
    deg = np.bincount(flat, minlength=n_vertices).tolist()  # not-yet-emitted incident faces
    fl = faces.tolist()
    alive = [True] * n_faces
    seq: list[int] = []
    starts: list[int] = []
    p = 0
    # One Python iteration per patch, a few per face: fans are small (about 6 faces).
    while True:
        while p < n_faces and not alive[p]:
            p += 1
        if p == n_faces:
            break
        a, b, c = fl[p]
        centre = a
        if deg[b] > deg[centre]:
            centre = b
        if deg[c] > deg[centre]:
            centre = c
        edges = _fan_edges(centre, inc[bounds[centre]:bounds[centre + 1]], alive, fl)
        chain, used = _walk_directed(edges) if oriented else _walk_undirected(edges, centre, fl)
        starts.append(len(seq))
        seq.append(centre)
        seq.extend(chain)
        for fi in used:
            alive[fi] = False
            x, y, z = fl[fi]
            deg[x] -= 1
            deg[y] -= 1
            deg[z] -= 1
    return seq, starts


def _fan_edges(centre: int, incident: list[int], alive: list[bool], fl: list[list[int]]
               ) -> list[tuple[int, int, int]]:
    """The fan of ``centre``'s faces not yet emitted: (u, v, face) per face, which is (centre, u, v) in its
    winding."""
    edges = []
    for fi in incident:
        if alive[fi]:
            x, y, z = fl[fi]
            if x == centre:
                edges.append((y, z, fi))
            elif y == centre:
                edges.append((z, x, fi))
            else:
                edges.append((x, y, fi))
    return edges


def _walk_directed(edges: list[tuple[int, int, int]]) -> tuple[list[int], list[int]]:
    """Chain along directed edges u -> v from the smallest vertex no edge enters (any vertex of a
    closed fan); at a branch (non-manifold fan) the smallest target is taken, the rest waits."""
    out: dict[int, list[tuple[int, int]]] = {}
    heads = set()
    for u, v, fi in edges:
        out.setdefault(u, []).append((v, fi))
        heads.add(v)
    free = [u for u in out if u not in heads]
    cur = min(free) if free else min(out)  # open fan: its first vertex; closed fan: any
    for lst in out.values():
        lst.sort(reverse=True)  # pop() takes the smallest target first
    chain, used = [cur], []
    while out.get(cur):
        v, fi = out[cur].pop()
        used.append(fi)
        chain.append(v)
        cur = v
    return chain, used


def _walk_undirected(edges, centre: int, fl: list[list[int]]) -> tuple[list[int], list[int]]:
    """The authors' walk: undirected edges, start at a chain end (lowest), orient by the first face."""
    nb: dict[int, list[tuple[int, int, int]]] = {}
    for u, v, fi in sorted((min(u, v), max(u, v), fi) for u, v, fi in edges):
        nb.setdefault(u, []).append((u, v, fi))
        nb.setdefault(v, []).append((u, v, fi))
    ends = [x for x, lst in nb.items() if len(lst) == 1]
    cur = min(ends) if ends else min(nb)
    chain, used, seen = [cur], [], set()
    while True:
        step = next(((u, v, fi) for u, v, fi in nb[cur] if fi not in seen), None)
        if step is None:
            break
        u, v, fi = step
        seen.add(fi)
        used.append(fi)
        cur = v if cur == u else u
        chain.append(cur)
    x, y, z = fl[used[0]]
    rot = {(x, y, z), (y, z, x), (z, x, y)}
    if (centre, chain[0], chain[1]) not in rot:
        chain.reverse()
    return chain, used


def encode(q: np.ndarray, faces: np.ndarray, oriented: bool = True,
           first_block_explicit: bool = False) -> np.ndarray:
    """Quantised mesh -> int64 BPT tokens (BOS ... EOS).

    Parameters
    ----------
    q : (V, 3) int
        Cells in [0, 127].
    faces : (F, 3) int
    oriented : bool
        Winding-exact chains (see module docstring).
    first_block_explicit : bool
        Always write the first chain vertex's block (the authors' token count).
    """
    q, f = canonical_mesh(q, faces)
    seq, starts = patchify(f, len(q), oriented=oriented)
    seq = np.asarray(seq, dtype=np.int64)
    block, offset = split_cells(q[seq])
    is_centre = np.zeros(len(seq), dtype=bool)
    is_centre[starts] = True
    new_block = is_centre.copy()
    new_block[1:] |= block[1:] != block[:-1]
    if first_block_explicit:
        new_block[1:] |= is_centre[:-1]
    out = np.empty(len(seq) + int(new_block.sum()) + 2, dtype=np.int64)
    out[0], out[-1] = BOS, EOS
    pos_off = np.arange(len(seq)) + np.cumsum(new_block) + 1
    out[pos_off] = OFFSET0 + offset
    pos_blk = pos_off[new_block] - 1
    out[pos_blk] = np.where(is_centre[new_block], PATCH0, BLOCK0) + block[new_block]
    return out


def decode(tokens: np.ndarray, strict: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """BPT tokens -> canonical (q, faces).

    BOS/PAD are skipped and decoding stops at EOS.  With ``strict``, malformed input
    (an offset before any patch token, a patch with fewer than two chain vertices, ids
    outside the vocabulary) raises ValueError; otherwise the malformed parts are dropped.
    """
    t = np.asarray(tokens, dtype=np.int64).ravel()
    stop = np.flatnonzero(t == EOS)
    if len(stop):
        t = t[: stop[0]]
    t = t[t >= N_SPECIAL]
    if len(t) and t.max() >= VOCAB_SIZE:
        if strict:
            raise ValueError(f"token id {int(t.max())} outside the BPT vocabulary ({VOCAB_SIZE})")
        t = t[t < VOCAB_SIZE]
    is_patch = t >= PATCH0
    is_block = (t < OFFSET0) | is_patch
    patch_id = np.cumsum(is_patch) - 1  # -1 before the first patch token
    # Current block of every token: the value of the last block token at or before it.
    blk_val = np.where(is_patch, t - PATCH0, t - BLOCK0)
    last_blk = np.maximum.accumulate(np.where(is_block, np.arange(len(t)), -1)) if len(t) else t
    is_off = ~is_block
    ok = is_off & (patch_id >= 0)
    if strict and not ok[is_off].all():
        raise ValueError("offset token before the first patch token")
    keys = blk_val[last_blk[ok]] * N_OFFSETS + (t[ok] - OFFSET0)
    pid = patch_id[ok]
    cells = cells_from_keys(keys)
    # The first vertex of each patch is its centre; consecutive chain vertices make a face.
    first = np.ones(len(pid), dtype=bool)
    first[1:] = pid[1:] != pid[:-1]
    centre_pos = np.maximum.accumulate(np.where(first, np.arange(len(pid)), 0)) if len(pid) else pid
    sizes = np.bincount(pid, minlength=int(is_patch.sum()))
    if strict and (sizes < 3).any():
        raise ValueError("a patch needs a centre and at least two chain vertices")
    j = np.flatnonzero(~first[:-1] & ~first[1:]) if len(pid) > 1 else np.zeros(0, dtype=np.int64)
    corners = np.stack([cells[centre_pos[j]], cells[j], cells[j + 1]], axis=1)
    return mesh_from_soup(corners.reshape(-1, 3))


def num_tokens(q: np.ndarray, faces: np.ndarray, oriented: bool = True,
               first_block_explicit: bool = False) -> int:
    """Length of ``encode(q, faces, ...)`` (BOS and EOS included)."""
    return len(encode(q, faces, oriented=oriented, first_block_explicit=first_block_explicit))

