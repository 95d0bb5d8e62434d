"""Steps 2-7 for one candidate: the input encoded, its vertex tokens decoded (as part of a batch), positions
inside the cells and fitted to the input's planes, edges predicted and filtered, triangles chosen on the
input surface.  :class:`CandidateSteps` is a part of :class:`fastmesh.pipeline.Pipeline` (its networks and
settings)."""

from __future__ import annotations

from collections.abc import Callable, Generator
from dataclasses import replace

import numpy as np
import torch

from ..batch import DecodeRequest
from ..export.quads import EdgeEvidence
from ..faces import mesh_from_adjacency
from ..faces.decimation import quadric_decimation
from ..faces.facecount import CountRule, count_rule
from ..faces.filtering import predict_edges
from ..faces.meshops import weld
from ..faces.missed import missed_points
from ..faces.solid import solid_mesh
from ..faces.support import weighed_fit
from ..fitting import distinct, fit_radius, fit_samples, fit_to_planes
from ..models.cells import raise_cells, snap_to_cells, vertex_probabilities
from ..models.generate import GenerationError
from ..params import GenerateParams
from ..request import Frame, Request
from ..shapes.corners import mesh_corners
from ..tokenizer import dequantize
from ..tokenizer import vertex as vt
from ..tokenizer.grid import CELL, quantize, sort_key
from .runtime import stage, timed_passes

CELL_SEED = 0  # of the input sample the cell evidence reads
# An input point added as a vertex moves to the best-scored cell around it (``_missed_cells``): on 14 held-out
# characters and aircraft, vertex precision 0.40 -> 0.46 and CD 0.99 -> 0.97 against the point's own cell.
MISSED_SNAP = 0.0
# ... and the mesh made with them comes back only where its weighed_fit is under this share of the model's own:
# the vertices cost faces (up to half as many again), and smooth shapes the decoder made well gain 6-7 % for
# them (a torus, a wavy sheet) where the slabs and cut-off wings of characters and aircraft gain 11-59 %.
MISSED_MARGIN = 0.9


class CandidateSteps:
    """One candidate's steps, from the input encoded to its triangles (see the module)."""

    def tells(self, params: GenerateParams, logodds: torch.Tensor | None) -> bool:
        """Whether the decoder is told ``params.target_faces``: always with ``SamplingConfig.read_count``, else
        where it has the count token and the target lies under ``tell_below`` x the vertices the cell log-odds
        ``logodds`` (1, 128^3) expect."""
        sampling, target = params.sampling(self.max_vertices), params.target_faces
        if target is None or sampling.read_count:
            return target is not None
        return bool(self.vertex.cfg.count_condition and logodds is not None
                    and target < sampling.tell_below * float(vertex_probabilities(logodds.float()).sum()))

    def _target(self, params: GenerateParams, told: bool = True) -> torch.Tensor | None:
        """(1,) faces asked for, as the decoder's count token reads them, where it is ``told`` them; None: the
        model's choice.  A decoder without the token refuses a target told."""
        if params.target_faces is None or not told:
            return None
        if not self.vertex.cfg.count_condition:
            raise ValueError("target_faces: this vertex decoder was not trained with a face-count condition")
        return torch.tensor([params.target_faces], device=self.device)

    def _logodds(self, frame: Frame, params: GenerateParams | None = None, corners: np.ndarray | None = None
                 ) -> torch.Tensor | None:
        """(1, 128^3) cell log-odds of the input in ``frame`` for a decoder that reads them (``models.cells``),
        else None; a mesh input's corners (``corners`` (K, 3) in ``frame``'s unit cube, found in ``frame`` when
        not given: :meth:`_corners`) raised to ``params``' ``SamplingConfig.corner_logodds``.

        Evidence about the input, not a random choice: drawn from one sample of fixed seed, so every
        candidate reads the same grid and candidate k stays exactly what seed + k gives alone.
        """
        if not self.vertex.cfg.evidence_cells:
            return None
        pts, nrm = frame.samples(self.cell_net.cfg.n_points, CELL_SEED)
        grid = self.cell_net.grid(pts, nrm)[None].to(self.device)
        corner = (params or GenerateParams()).sampling(self.max_vertices).corner_logodds
        if corner is None or frame.shape.faces is None:
            return grid
        return raise_cells(grid, self._corners(frame) if corners is None else corners, corner)

    @staticmethod
    def _corners(frame: Frame) -> np.ndarray:
        """(K, 3) float64 corners of ``frame``'s mesh (``shapes.corners``) in its unit cube."""
        return mesh_corners(*weld(frame.unit, frame.shape.faces))

    def _encode(self, frame: Frame, seed: int, params: GenerateParams, logodds: torch.Tensor | None = None,
                told: bool = False) -> tuple:
        """The surface sample of ``seed`` in ``frame`` (points, normals: (n, 3) float32 in its unit cube) and the
        vertex decoder's condition on it: (points, normals, prefix (1, M, dim), evidence); ``logodds`` from
        :meth:`_logodds`; ``told``: the decoder reads ``params.target_faces`` (:meth:`tells`)."""
        pts, nrm = frame.samples(self._n_points(), seed)
        n_vp = self.vertex.cfg.encoder.n_points
        pts_t = torch.from_numpy(pts).to(self.device)[None, :n_vp]
        nrm_t = torch.from_numpy(nrm).to(self.device)[None, :n_vp]
        with torch.inference_mode():
            target = self._target(params, told)
            prefix = self.vertex.condition(pts_t, nrm_t, target)
            evidence = self.vertex.point_evidence(pts_t, nrm_t, logodds, target)
        return pts, nrm, prefix, evidence

    def _decode(self, req: Request, frames: list[Frame], report: Callable[[float], None]
                ) -> Generator[DecodeRequest, list[torch.Tensor], list[tuple]]:
        """Vertex tokens of every frame's candidates ``params.seed`` ... ``params.seed + n_cand - 1`` (their
        ``encoded`` conditions, from :meth:`_frame`), decoded as one batch: a second frame's rows ride with the
        first's instead of decoding after them.

        Candidate k of a frame reads its own surface sample (seed + k) and samples with seed + k: it is what that
        seed gives alone, in whatever batch (``models.generate``: each row keeps its seed, evidence and grammar
        state).  Yields the :class:`DecodeRequest` of the candidates and is sent their sequences
        (:class:`fastmesh.batch.Batch` decodes it and calls the request's ``progress``, here ``report(share)`` of the
        vertices decoded; the job's clock is in ``vertices`` meanwhile); returns per candidate, frame
        after frame, its (points, normals, tokens).
        """
        req.check()
        encoded = [e for frame in frames for e in frame.encoded]
        seeds = [req.params.seed + k for frame in frames for k in range(len(frame.encoded))]
        evidence = [ev for _, _, _, ev in encoded]
        sampling = req.params.sampling(self.max_vertices)
        max_v = sampling.max_vertices

        def on_step(n_vert: int) -> None:
            report(min(1.0, n_vert / max_v))

        report(0.0)
        # ``vertices`` until the rows come back: in a batch that includes the wait for the round's other jobs, so
        # every second of the job is in one stage.
        req.timings.enter("vertices")
        seqs = yield DecodeRequest(torch.cat([prefix for _, _, prefix, _ in encoded]),
                                   None if evidence[0] is None else evidence, sampling, seeds, on_step,
                                   req.should_cancel)
        return [(pts, nrm, seq.cpu().numpy()) for (pts, nrm, _, _), seq in zip(encoded, seqs, strict=True)]

    def vertex_cells(self, tokens: np.ndarray, logodds: torch.Tensor | None, params: GenerateParams,
                     count: CountRule | None = None) -> np.ndarray:
        """(N, 3) int64 vertex cells of the decoder's ``tokens``, moved by the cell log-odds ``logodds`` (from
        :meth:`_logodds`) where ``SamplingConfig.snap_margin`` says so (``models.cells.snap_to_cells``) and
        the face-count rule allows it (``count``, made from ``params`` when not given: not with a target told to the
        decoder)."""
        q = vt.decode(tokens, strict=True)
        sampling = params.sampling(self.max_vertices)
        margin = sampling.snap_margin
        count = count or count_rule(params.target_faces, sampling.read_count)
        if logodds is None or margin is None or not count.snap:
            return q
        return snap_to_cells(q, logodds[0].cpu(), margin)

    def _fit(self, frame: Frame, positions: np.ndarray, seed: int) -> np.ndarray:
        """``positions`` (N, 3) moved onto the planes of the input around them (``fitting.fit_to_planes``)."""
        from scipy.spatial import cKDTree

        pts, nrm = fit_samples(frame.shape, frame.unit, self.fit_config, seed, draw=frame.samples)
        tree = cKDTree(pts)
        cfg = self.fit_config
        return fit_to_planes(positions, pts, nrm, fit_radius(cfg, pts, tree), cfg.rel, tree, cfg.reach)

    def _positions(self, req: Request, frame: Frame, k: int) -> tuple | GenerationError:
        """Candidate ``k`` of the frame as vertex cells and positions in its unit cube: ``(cells (N, 3) int64,
        positions (N, 3), vertices decoded)``, or the GenerationError that stops it; timed as the enhancer."""
        pts, nrm, tokens = frame.decoded[k]
        q = self.vertex_cells(tokens, frame.logodds, req.params, req.count)
        if len(q) < 3:
            return GenerationError("no_vertices", f"the vertex decoder produced {len(q)} vertices; try another seed")
        decoded = len(q)
        req.check()
        # Fidelity enhancer: continuous positions inside each cell.
        with stage("enhancer", req.timings):
            if req.params.enhancer:
                n_ep = self.enhancer.cfg.encoder.n_points
                positions = self.enhancer.refine(q, pts[:n_ep], nrm[:n_ep])
            else:
                positions = dequantize(q)
            if self.fit_config.radius is not None:
                positions = self._fit(frame, positions, req.params.seed + k)
                if self.fit_config.merge is not None:  # vertices fitted onto one point become one
                    keep = distinct(positions, self.fit_config.merge * CELL)
                    q, positions = q[keep], positions[keep]
                    if len(q) < 3:
                        return GenerationError("no_vertices", f"the vertex decoder's {decoded} vertices lie on "
                                               f"{len(q)} points of the surface; try another seed")
        return q, positions, decoded

    def _faces(self, req: Request, frame: Frame, k: int, report: Callable[[float], None] | None
               ) -> dict | GenerationError:
        """Candidate ``k``'s mesh in the frame's unit cube from its :meth:`_positions`, its holes closed where
        the request closes (``req.close``), or the GenerationError that stopped it; ``report(share)`` follows the
        filtering passes (None without filtering).  Adds its stage times to ``req.timings``."""
        placed = frame.positions[k]
        if isinstance(placed, GenerationError):
            return placed
        q, positions, decoded = placed
        made = self._connect(req, frame, k, q, positions, report)
        return made if isinstance(made, GenerationError) else {**made, "generated_vertices": decoded}

    def _connect(self, req: Request, frame: Frame, k: int, q: np.ndarray, positions: np.ndarray,
                 report: Callable[[float], None] | None) -> dict | GenerationError:
        """Steps 5-7 for candidate ``k`` of the frame on vertex cells ``q`` (N, 3) at ``positions`` (N, 3) in its
        unit cube: its mesh (vertices, faces, tokens, edges, evidence), or the GenerationError of no faces."""
        pts, nrm, tokens = frame.decoded[k]
        timings = req.timings
        req.check()
        # Stage II: edges in one bidirectional pass, then (optionally) filtered re-predictions.
        n_fp = self.face.cfg.encoder.n_points
        with stage("faces", timings):
            predict = self.face.predictor(q, pts[:n_fp], nrm[:n_fp])  # encodes the condition once
        predict = timed_passes(predict, timings, report or (lambda share: None), req.should_cancel,
                         self.filter_config.n_passes)
        edges, logits = predict_edges(predict, len(q), self.filter_config, req.params.filtering)

        # Triangles on the input surface, scored by the edge logits, kept a surface, holes closed, flat vertices
        # removed (but not where a face-count target was told to the decoder: ``req.count.remove_flat``).
        with stage("faces", timings):
            tc = replace(self.triangle_config, close=req.close, close_everywhere=req.sealed)
            if not req.count.remove_flat:  # the decoder made them for the count told: flat regions keep them
                tc = replace(tc, flat_tol=None)
            surface = None
            if tc.support_tol is not None or tc.max_faces_per_edge is not None or tc.selection == "surface":
                surface = frame.surface(tc.support_points, req.params.seed + k)
            verts, faces = mesh_from_adjacency(positions, edges, tc, points=surface, logits=logits, oriented=(pts, nrm))
            solid = {}
            # The boundary of a solid, weighed against the selection's mesh (an open input's with ``solid_open``:
            # what it encloses, cut as a closed input's, the parts that enclose nothing patched in from the mesh, then
            # its faces across the input's openings taken off).
            # Point clouds only: on a mesh input's quadric vertices the cut rounds sharp rims (a faceted cylinder's
            # HD 0.4 -> 1.8 %), and its own decimation is the clean rival there (step 8).
            if tc.solid is not None and req.shape.faces is None and (req.close or req.sealed or tc.solid_open):
                verts, faces, solid = solid_mesh(positions, pts, nrm, edges, logits, (verts, faces), surface,
                                                 tc.solid, tc.flat_tol, req.params.seed + k, tc.solid_patch,
                                                 open_=not (req.close or req.sealed))
        if len(faces) == 0:
            return GenerationError("no_faces", f"the face model connected no triangles among {len(q)} vertices")
        return {"vertices": verts, "faces": faces, "tokens": int(len(tokens)), "edges": int(len(edges)),
                "evidence": EdgeEvidence.of_mesh(verts, faces, positions, logits, edges),
                **({"solid_fits": solid} if solid else {})}

    def _missed_cells(self, frame: Frame, points: np.ndarray, seed: int) -> tuple[np.ndarray, np.ndarray]:
        """Input ``points`` (K, 3) the mesh left out as vertices: their cells moved to the cell the evidence scores
        best among their own and the 26 around it (``models.cells.snap_to_cells``, margin ``MISSED_SNAP``), and
        those cells' centres fitted to the input's planes as the decoder's are; (M, 3) cells and positions."""
        cells = quantize(points)
        if frame.logodds is None:
            return cells, points
        cells = snap_to_cells(cells, frame.logodds[0].cpu(), MISSED_SNAP)
        positions = dequantize(cells)
        return cells, positions if self.fit_config.radius is None else self._fit(frame, positions, seed)

    def _with_missed(self, req: Request, frame: Frame, best: dict) -> dict:
        """The frame's chosen mesh ``best`` (candidate ``best["k"]``, its ``fit`` against ``frame.reference`` where
        there are several) made again with the input points it leaves out among its vertices
        (``missed.missed_points``: at most ``TriangleConfig.add_missed`` x its vertices, each farther than
        ``missed_tol`` from it; ``_missed_cells``), where that mesh lies nearer the input by ``MISSED_MARGIN``
        (``support.weighed_fit``).  The mesh kept, with ``added_vertices`` (how many of its vertices came from
        the input) and, where weighed, ``missed_fits`` (both fits); ``best`` where none is missed or the request
        tells the decoder a face count (the count it aimed for).  The vertices stay within the request's
        ``max_vertices``."""
        tc, k = self.triangle_config, best["k"]
        q, positions = best["cells"], best["positions"]
        budget = req.params.sampling(self.max_vertices).max_vertices  # the request's, the face stage's memory
        room = 0 if tc.add_missed is None else min(int(tc.add_missed * len(q)), budget - len(q))
        if room <= 0 or req.count.told:
            return {**best, "added_vertices": 0}
        seed = req.params.seed
        with stage("weighing", req.timings):
            reference = frame.surface(tc.support_points, seed)
            extra = missed_points(best["vertices"], best["faces"], reference, tc.missed_tol, room, seed)
            cells, extra = self._missed_cells(frame, extra, seed)
            new = ~(cells[:, None] == q[None]).all(-1).any(1)  # a cell the decoder gave already stays its own
            if self.fit_config.merge is not None:  # and so does a point of the surface the fit put a vertex on
                keep = distinct(np.concatenate([positions, extra]), self.fit_config.merge * CELL)
                new &= np.isin(np.arange(len(extra)) + len(q), keep)
            extra, cells = extra[new], cells[new]
        made = None
        if len(extra):
            made = self._connect(req, frame, k, np.concatenate([q, cells]), np.concatenate([positions, extra]), None)
        if made is None or isinstance(made, GenerationError):
            return {**best, "added_vertices": 0}
        with stage("weighing", req.timings):
            fits = self._weighed(frame, seed, best, made, ("model", "with_missed"))
        if fits["with_missed"] >= MISSED_MARGIN * fits["model"]:
            return {**best, "added_vertices": 0, "missed_fits": fits}
        return {**best, **made, "fit": fits["with_missed"], "cells": np.concatenate([q, cells]),
                "positions": np.concatenate([positions, extra]), "added_vertices": int(len(extra)), "missed_fits": fits}

    def _with_quadrics(self, req: Request, frame: Frame, best: dict) -> dict:
        """A mesh input's chosen mesh ``best`` (candidate ``best["k"]``, its ``fit`` against ``frame.reference``
        where there are several) against the mesh the face stage makes on the vertices of the input's quadric
        decimation to ``best``'s face count (``decimation.quadric_decimation``): the one nearer the input
        (``support.weighed_fit``), with ``vertices_from`` ("decoder" or "quadrics") and, where weighed,
        ``quadric_fits`` (both fits).  A dense mesh's quadrics put its vertices on its corners and creases,
        where an artist's lie; the face stage still makes the mesh an asset (closed, one piece, manifold).
        Before ``_with_missed``, which adds to whichever is kept."""
        best = {**best, "vertices_from": "decoder"}
        if not self.triangle_config.quadric_vertices or frame.shape.faces is None:
            return best
        budget = req.params.sampling(self.max_vertices).max_vertices
        with stage("weighing", req.timings):
            v, _ = quadric_decimation(frame.unit, frame.shape.faces, len(best["faces"]))
            cells = quantize(v)
            _, first = np.unique(sort_key(cells), return_index=True)  # the decoder's order, a vertex per cell
        if not 3 <= len(first) <= budget:
            return best
        made = self._connect(req, frame, best["k"], cells[first], v[first], None)
        if isinstance(made, GenerationError):
            return best
        with stage("weighing", req.timings):
            fits = self._weighed(frame, req.params.seed, best, made, ("decoder", "quadrics"))
        if fits["quadrics"] >= fits["decoder"]:
            return {**best, "quadric_fits": fits}
        return {**best, **made, "fit": fits["quadrics"], "cells": cells[first], "positions": v[first],
                "vertices_from": "quadrics", "quadric_fits": fits}

    def _weighed(self, frame: Frame, seed: int, best: dict, made: dict, names: tuple[str, str]) -> dict[str, float]:
        """``support.weighed_fit`` of the frame's chosen mesh ``best`` and of its rival ``made`` against the input's
        sample of ``TriangleConfig.support_points`` at ``seed``, under ``names``, to 6 places.  The candidates were
        weighed against this same draw (``frame.reference``, where there are several): the chosen one's fit is
        known."""
        reference = frame.surface(self.triangle_config.support_points, seed)
        known = best["fit"] if frame.reference is not None else None
        return {name: round(weighed_fit(m["vertices"], m["faces"], reference, seed) if fit is None else fit, 6)
                for name, m, fit in zip(names, (best, made), (known, None), strict=True)}
