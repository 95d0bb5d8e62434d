"""Training sets: folders of mesh files -> one compact, quickly loaded cache file.

Each mesh is normalised into the unit cube, quantised to 7 bits, merged, cleaned and
put in canonical vertex order (``tokenizer.quantize_mesh``).  The cache is a single
uncompressed ``.npz`` of concatenated arrays plus offsets, so loading is a handful of
``memcpy``s (well under a second for the whole corpus).

Validation holds out whole *packages* (``VAL_PACKAGES``): meshes of one game share authors,
tools and style, so a split inside the packages lets a model score on the style it was trained on
(our decoder scored about 30 % better there than on packages it had never seen).  Without
held-out packages the split is by *group* (a pose and its base mesh share one group) and
deterministic: a group is in validation when ``crc32(group) % 1000 < 1000 * val_fraction``.
"""

from __future__ import annotations

import csv
import json
import os
import zlib
from collections import Counter
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..shapes.io import load_shape
from ..shapes.shape import MESH_FORMATS, Normalization, ShapeError
from ..tokenizer import dequantize, quantize_mesh, vertex
from ..tokenizer.grid import LEVELS

CACHE_VERSION = 2

# Packages of ../shared/corpus held out for validation: 693 of its 6,420 files (10.8 %), four games
# unlike each other and unlike the rest: an RTS's low-poly units and buildings (warzone2100), racing
# cars and tracks (torcs), aircraft and ships of a flight simulator (flightgear-data-ai), and an arena
# shooter's characters and weapons (all three openarena packages, one game).  Not sweethome3d-furniture:
# it is our only furniture.
VAL_PACKAGES = ("warzone2100-data", "torcs-data", "flightgear-data-ai", "openarena-data", "openarena-085-data",
                "openarena-088-data")


@dataclass
class MeshRecord:
    """One quantised mesh of a dataset.

    Attributes
    ----------
    q : (V, 3) int64 cells, canonical order
    faces : (F, 3) int64
    residual : (V, 3) float32, continuous position minus cell centre, in cells ([-0.5, 0.5])
    name, group, category, package : str
    """

    q: np.ndarray
    faces: np.ndarray
    residual: np.ndarray
    name: str
    group: str
    category: str = ""
    package: str = ""

    @property
    def continuous(self) -> np.ndarray:
        """(V, 3) float64 normalised positions (cell centre + residual)."""
        return dequantize(self.q) + self.residual / LEVELS


class MeshDataset:
    """A loaded cache: random access to :class:`MeshRecord` by index."""

    def __init__(self, arrays: dict[str, np.ndarray], meta: dict):
        self.arrays = arrays
        self.meta = meta

    def __len__(self) -> int:
        return len(self.arrays["v_off"]) - 1

    def __getitem__(self, i: int) -> MeshRecord:
        a = self.arrays
        v0, v1 = a["v_off"][i], a["v_off"][i + 1]
        f0, f1 = a["f_off"][i], a["f_off"][i + 1]
        return MeshRecord(q=a["q"][v0:v1].astype(np.int64), faces=a["faces"][f0:f1].astype(np.int64),
                          residual=a["residual"][v0:v1].astype(np.float32), name=str(a["name"][i]),
                          group=str(a["group"][i]), category=str(a["category"][i]), package=str(a["package"][i]))

    def cells(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """Mesh ``i``'s stored cells (a cache of ``build_cell_cache``): flat indices (K,) int32 and
        log-odds (K,) float16."""
        if "c_off" not in self.arrays:
            raise ValueError("this dataset holds no cell log-odds: build it with `fastmesh data cells`")
        c0, c1 = self.arrays["c_off"][i], self.arrays["c_off"][i + 1]
        return self.arrays["cell_flat"][c0:c1], self.arrays["cell_logit"][c0:c1]

    def cell_logits(self, i: int):
        """(128^3,) float32 torch grid of mesh ``i``'s stored cell log-odds."""
        from ..models.cells import dense_grid_flat

        return dense_grid_flat(*self.cells(i))

    def num_vertices(self) -> np.ndarray:
        return np.diff(self.arrays["v_off"])

    def num_faces(self) -> np.ndarray:
        return np.diff(self.arrays["f_off"])

    def indices(self, split: str) -> np.ndarray:
        """Indices of ``'train'``, ``'val'`` or ``'all'`` records."""
        if split == "all":
            return np.arange(len(self))
        return np.flatnonzero(self.arrays["split"] == (1 if split == "val" else 0))


def subset_arrays(ds: MeshDataset, indices: np.ndarray) -> dict[str, np.ndarray]:
    """The arrays of a dataset holding only the meshes at ``indices`` (in that order), ``meta`` included."""
    a = ds.arrays
    v = np.concatenate([np.arange(a["v_off"][i], a["v_off"][i + 1]) for i in indices])
    f = np.concatenate([np.arange(a["f_off"][i], a["f_off"][i + 1]) for i in indices])
    out = {"q": a["q"][v], "residual": a["residual"][v], "faces": a["faces"][f],
           "v_off": np.concatenate([[0], np.cumsum(ds.num_vertices()[indices])]).astype(np.int64),
           "f_off": np.concatenate([[0], np.cumsum(ds.num_faces()[indices])]).astype(np.int64)}
    for k in ("name", "group", "category", "package", "split"):
        out[k] = a[k][indices]
    out["meta"] = np.array(json.dumps(ds.meta))
    return out


CELL_KEEP = -6.0  # cells scored below these log-odds are stored as models.cells.FLOOR


def build_cell_cache(ds: MeshDataset, net, out: str | os.PathLike, per_split: dict[str, int], seed: int = 0,
                     progress=None, workers: int = 1) -> int:
    """A dataset of some meshes plus the cell evidence network's log-odds for each (unaugmented).

    The vertex decoder reads these log-odds (``VertexConfig.evidence_cells``); scoring a mesh's
    cells costs about a second on a CPU core, too slow to do per training batch, so they are
    computed once per mesh, from ``net.cfg.n_points`` surface samples drawn with ``seed``
    (the same whatever ``workers``, processes that score meshes side by side).

    Parameters
    ----------
    per_split : {"train": n, "val": m}: how many meshes of each split (a seeded random choice).

    Returns the number of meshes written.  The cache holds ``cell_flat`` (int32 flat cell index),
    ``cell_logit`` (float16) and ``c_off`` (offsets per mesh) beside the usual arrays.
    """
    import multiprocessing as mp

    rng = np.random.default_rng(seed)
    chosen = np.concatenate([rng.permutation(ds.indices(split))[:n] for split, n in per_split.items()])
    _CELL_JOB.update(ds=ds, net=net, seed=seed)
    try:
        if workers > 1:
            with mp.get_context("fork").Pool(workers, initializer=one_thread) as pool:
                scored = list(_progress(pool.imap(_score_mesh, chosen.tolist(), chunksize=4), len(chosen), progress))
        else:
            scored = list(_progress(map(_score_mesh, chosen.tolist()), len(chosen), progress))
    finally:
        _CELL_JOB.clear()
    flats, logits = zip(*scored, strict=True) if scored else ((), ())
    arrays = subset_arrays(ds, chosen)
    arrays.update(cell_flat=np.concatenate([np.zeros(0, np.int32), *flats]),
                  cell_logit=np.concatenate([np.zeros(0, np.float16), *logits]),
                  c_off=np.concatenate([[0], np.cumsum([len(f) for f in flats])]).astype(np.int64))
    Path(out).parent.mkdir(parents=True, exist_ok=True)
    with open(out, "wb") as fh:
        np.savez(fh, **arrays)
    return len(chosen)


_CELL_JOB: dict = {}  # dataset, network and seed of build_cell_cache (inherited by forked workers)


def one_thread() -> None:
    """Initializer of a worker process: one torch thread, so that the workers together use the machine."""
    import torch

    torch.set_num_threads(1)


def _score_mesh(i: int) -> tuple[np.ndarray, np.ndarray]:
    """Flat indices (int32) and log-odds (float16) of mesh ``i``'s cells at or above ``CELL_KEEP``."""
    from ..models.cells import flat_index
    from ..shapes.io import sample_triangles

    ds, net, seed = _CELL_JOB["ds"], _CELL_JOB["net"], _CELL_JOB["seed"]
    rec = ds[int(i)]
    pts, nrm = sample_triangles(rec.continuous, rec.faces, net.cfg.n_points, np.random.default_rng([seed, int(i)]))
    cells, lo = net.score(pts, nrm)
    keep = lo >= CELL_KEEP
    return flat_index(cells[keep]).numpy().astype(np.int32), lo[keep].numpy().astype(np.float16)


def _progress(items, total: int, progress):
    for k, item in enumerate(items):
        if progress:
            progress(k + 1, total)
        yield item


def load_dataset(path: str | os.PathLike) -> MeshDataset:
    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    meta = json.loads(str(arrays.pop("meta")))
    if meta.get("version") != CACHE_VERSION:
        raise ValueError(f"{path}: cache version {meta.get('version')} != {CACHE_VERSION}; rebuild it")
    return MeshDataset(arrays, meta)


def in_validation(group: str, val_fraction: float) -> bool:
    return zlib.crc32(group.encode("utf-8")) % 1000 < round(1000 * val_fraction)


# --------------------------------------------------------------------------- building


def _find_files(sources: list[str]) -> list[tuple[str, str, str, str]]:
    """(path, group, category, package) for every mesh file under ``sources``.

    A ``manifest.csv`` with ``file`` and ``group`` columns at the top of a source
    folder (as in our corpus) supplies groups, categories and packages; otherwise each
    file is its own group and its package is its top folder under the source.
    """
    out = []
    for src in sources:
        p = Path(src)
        if p.is_file():
            out.append((str(p), p.name, "", ""))
            continue
        if not p.is_dir():
            raise FileNotFoundError(f"no such file or folder: {src}")
        manifest = {}
        mf = p / "manifest.csv"
        if mf.exists():
            with open(mf, newline="") as fh:
                for row in csv.DictReader(fh):
                    if "file" in row:
                        manifest[row["file"]] = (row.get("group") or row["file"], row.get("category", ""),
                                                 row.get("package", ""))
        for f in sorted(p.rglob("*")):
            if f.is_file() and f.suffix.lower().lstrip(".") in MESH_FORMATS:
                rel = f.relative_to(p).as_posix()
                top = rel.split("/")[0] if "/" in rel else ""
                group, cat, package = manifest.get(rel, (rel, "", top))
                out.append((str(f), f"{p.name}/{group}", cat, package or top))
    return out


def _process(args: tuple[str, str, str, str, int]):
    path, group, category, package, max_vertices = args
    try:
        shape = load_shape(path)
    except ShapeError as e:
        return ("error", path, e.code)
    if shape.faces is None:
        return ("error", path, "not_a_mesh")
    v = Normalization.fit(shape.vertices).apply(shape.vertices)
    q, faces, cont = quantize_mesh(v, shape.faces)
    if len(faces) == 0:
        return ("error", path, "degenerate")
    if len(q) > max_vertices:
        return ("error", path, "too_many_vertices")
    residual = ((cont - dequantize(q)) * LEVELS).astype(np.float16)
    return ("ok", path, group, category, package, q.astype(np.uint8), faces.astype(np.int16), residual)


def build_dataset(sources: list[str], out: str | os.PathLike, max_vertices: int = 1000,
                  val_fraction: float = 0.05, val_packages: tuple[str, ...] | None = None,
                  missing_ok: bool = False, workers: int | None = None, progress=None) -> dict:
    """Build a cache from mesh files and write it to ``out``; return its statistics.

    Meshes that fail to load, exceed ``max_vertices`` after the 7-bit merge, or
    duplicate an earlier mesh exactly (same cells and faces) are dropped and counted.
    With ``val_packages`` (a non-empty tuple) the meshes of those packages are the
    validation split; with none (``()`` or None) a ``val_fraction`` of the groups is
    (0 puts every mesh in training).  A named package not among the sources is an error, or with
    ``missing_ok`` skipped (and with none of them there, the split is by group).
    """
    packages = tuple(val_packages or ())
    files = _find_files(list(sources))
    workers = workers or min(os.cpu_count() or 1, 8)
    if packages:
        unknown = sorted(set(packages) - {f[3] for f in files})
        if unknown and not missing_ok:
            raise ValueError(f"validation package(s) not found in the sources: {', '.join(unknown)}")
        packages = tuple(p for p in packages if p not in unknown)
    jobs = [(p, g, c, pkg, max_vertices) for p, g, c, pkg in files]
    results = []
    if workers > 1 and len(jobs) > 50:
        with ProcessPoolExecutor(workers) as ex:
            for i, r in enumerate(ex.map(_process, jobs, chunksize=32)):
                results.append(r)
                if progress and i % 500 == 0:
                    progress(i, len(jobs))
    else:
        results = [_process(j) for j in jobs]
    keep, dropped = _kept(results)
    if not keep:
        raise ValueError("no usable meshes found in " + ", ".join(map(str, sources)))
    names = [os.path.relpath(k[0], start=os.path.commonpath([str(s) for s in sources]) if len(sources) > 1
                             else (sources[0] if Path(sources[0]).is_dir() else Path(sources[0]).parent))
             for k in keep]
    split = [k[3] in packages if packages else in_validation(k[1], val_fraction) for k in keep]
    meta = {"version": CACHE_VERSION, "max_vertices": max_vertices,
            "val_packages": list(packages), "val_fraction": None if packages else val_fraction,
            "sources": [str(s) for s in sources], "dropped": dict(dropped)}
    Path(out).parent.mkdir(parents=True, exist_ok=True)
    with open(out, "wb") as fh:  # np.savez appends .npz to bare names; a handle keeps ``out`` exact
        np.savez(fh, **_cache_arrays(keep, names, split, meta))
    return dataset_stats(load_dataset(out))


def _kept(results: list[tuple]) -> tuple[list[tuple], Counter]:
    """The meshes of ``_process`` results that loaded, each (path, group, category, package, q, faces,
    residual), the first of exact duplicates (same cells and faces) only; and the dropped ones counted by why."""
    dropped: Counter = Counter()
    seen = set()
    keep = []
    for r in results:
        if r[0] != "ok":
            dropped[r[2]] += 1
            continue
        _, path, group, category, package, q, faces, residual = r
        h = (q.tobytes(), faces.tobytes())
        if h in seen:
            dropped["duplicate"] += 1
            continue
        seen.add(h)
        keep.append((path, group, category, package, q, faces, residual))
    return keep, dropped


def _cache_arrays(keep: list[tuple], names: list[str], split: list[bool], meta: dict) -> dict[str, np.ndarray]:
    """The cache's arrays: every kept mesh's cells, faces and residuals concatenated with their offsets, and
    per mesh its name, group, category, package and split; ``meta`` as JSON."""
    nv = np.array([len(k[4]) for k in keep])
    nf = np.array([len(k[5]) for k in keep])
    return {
        "q": np.concatenate([k[4] for k in keep]),
        "faces": np.concatenate([k[5] for k in keep]),
        "residual": np.concatenate([k[6] for k in keep]),
        "v_off": np.concatenate([[0], np.cumsum(nv)]).astype(np.int64),
        "f_off": np.concatenate([[0], np.cumsum(nf)]).astype(np.int64),
        "name": np.array(names),
        "group": np.array([k[1] for k in keep]),
        "category": np.array([k[2] for k in keep]),
        "package": np.array([k[3] for k in keep]),
        "split": np.array(split, dtype=np.uint8),
        "meta": np.array(json.dumps(meta)),
    }


def dataset_stats(ds: MeshDataset) -> dict:
    """Counts, vertex/face/token distributions and splits of a dataset."""
    nv, nf = ds.num_vertices(), ds.num_faces()
    blocks = []
    for i in range(len(ds)):
        r = ds[i]
        blocks.append(vertex.num_tokens(r.q))
    toks = np.array(blocks)
    split = ds.arrays["split"]

    def dist(x):
        return {"mean": float(x.mean()), "median": float(np.median(x)), "min": int(x.min()), "max": int(x.max()),
                "total": int(x.sum())}

    groups = ds.arrays["group"]
    return {
        "meshes": len(ds),
        "groups": int(len(np.unique(groups))),
        "train": int((split == 0).sum()),
        "val": int((split == 1).sum()),
        "val_groups": int(len(np.unique(groups[split == 1]))),
        "vertices": dist(nv),
        "faces": dist(nf),
        "fastmesh_tokens": dist(toks),
        "categories": dict(Counter(ds.arrays["category"].tolist()).most_common()),
        "val_packages": dict(Counter(ds.arrays["package"][split == 1].tolist()).most_common()),
        "max_vertices": ds.meta.get("max_vertices"),
        "dropped": ds.meta.get("dropped", {}),
    }
