"""The frames a request is generated in (the input's own and its canonical one) and the candidates in each:
every frame's candidates run stage by stage (:meth:`FrameSteps._in_frames`), the best candidate of a frame is
the one nearest the input surface, and the best frame the one whose result lies nearer it."""

from __future__ import annotations

from collections.abc import Generator

import numpy as np
import torch

from ..batch import DecodeRequest
from ..faces.facecount import count_rule
from ..faces.support import weighed_fit
from ..models.generate import GenerationError
from ..request import Frame, Request
from .candidate import CandidateSteps
from .runtime import stage

# A result made in the canonical frame (``canonical``) is kept unless its weighed_fit exceeds the input frame's
# by more than this factor.
FRAME_MARGIN = 1.1


class FrameSteps(CandidateSteps):
    """The steps over frames and their candidates (see the module); a part of :class:`fastmesh.pipeline.Pipeline`."""

    def _nearest_frame(self, req: Request, made: list[dict]) -> dict:
        """Of the results ``made`` in the input's frame and (last) in its canonical one, the canonical one
        unless its weighed_fit exceeds the other's by more than ``FRAME_MARGIN``: on a box both lie on its
        planes, but the turned one has its eight corners where the input's frame has a staircase of vertices
        along each wall."""
        if len(made) == 1:
            return made[0]
        seed = req.params.seed
        with stage("weighing", req.timings):
            reference = req.frame.surface(self.triangle_config.support_points, seed)
            fits = [weighed_fit(req.frame.norm.apply(m["vertices"]), m["faces"], reference, seed) for m in made]
        return made[-1] if fits[-1] <= FRAME_MARGIN * fits[0] else made[0]

    def _in_frames(self, req: Request, rotations: list[np.ndarray]
                   ) -> Generator[DecodeRequest, list[torch.Tensor], tuple[list[dict], list[GenerationError]]]:
        """The best of the candidates made with the input turned by each of ``rotations`` ((3, 3) each), turned
        back: per frame that made a mesh a dict of vertices (input frame), faces, tokens, info and rotation;
        and the errors of the frames that made none.

        Stage by stage over every frame and candidate (all encoded, all decoded, every enhancer, then the face
        stage), so that the progress passes each stage once; each frame's candidate k is still exactly what
        seed + k gives alone in that frame.  A :meth:`steps` generator: it yields each frame's decoding.
        """
        report = req.report
        frames = []
        for i, rotation in enumerate(rotations):
            report("encode", 0.0, i, len(rotations))
            frames.append(self._frame(req, rotation))
        decoded = yield from self._decode(req, frames, report.part("vertices", 0, 1))
        for frame in frames:
            frame.decoded, decoded = decoded[:len(frame.encoded)], decoded[len(frame.encoded):]
        work = [(frame, k) for frame in frames for k in range(len(frame.decoded))]
        req.timings.enter("enhancer")
        for j, (frame, k) in enumerate(work):
            report("enhancer", 0.0, j, len(work))
            frame.positions.append(self._positions(req, frame, k))
        req.timings.enter("faces")
        for j, (frame, k) in enumerate(work):
            report("faces", 0.0, j, len(work))
            parts = report.part("filtering", j, len(work)) if req.params.filtering else None
            frame.meshes.append(self._faces(req, frame, k, parts))
            report("faces", 1.0, j, len(work))
        made, errors = [], []
        req.timings.enter("weighing")  # the candidates, and the rivals of the chosen one (``_choose``)
        for frame in frames:
            try:
                made.append(self._choose(req, frame))
            except GenerationError as err:
                errors.append(err)
        return made, errors

    def _frame(self, req: Request, rotation: np.ndarray) -> Frame:
        """The input turned by ``rotation`` (the request's own frame for the identity) with what every stage
        reads of it: the reference the candidates are scored against (None for one candidate), and the cell
        evidence and candidates' encodings (``_encode``), timed as the encode stage."""
        frame = req.frame if np.array_equal(rotation, np.eye(3)) else Frame.of(req.shape, rotation)
        seed, n_cand = req.params.seed, req.candidates
        # Candidate k is exactly what seed + k gives alone; all are scored against one sample of the input.
        frame.reference = frame.surface(self.triangle_config.support_points, seed) if n_cand > 1 else None
        with stage("encode", req.timings):
            frame.logodds = self._logodds(frame, req.params, self._corners_in(req, frame))
            if frame is req.frame and not req.count.told and self.tells(req.params, frame.logodds):
                req.count = count_rule(req.params.target_faces, told=True)  # every frame reads the same count
            frame.encoded = [self._encode(frame, seed + k, req.params, frame.logodds, req.count.told)
                             for k in range(n_cand)]
        return frame

    def _corners_in(self, req: Request, frame: Frame) -> np.ndarray | None:
        """(K, 3) a mesh input's corners in ``frame``'s unit cube, found once per request in the input's own
        frame (``req.corners``) and turned: a second frame would find the same points a second time.  None for a
        point cloud or where the corners are not read."""
        reads = self.vertex.cfg.evidence_cells and req.params.sampling(self.max_vertices).corner_logodds is not None
        if req.shape.faces is None or not reads:
            return None
        if req.corners is None:
            req.corners = req.frame.norm.invert(self._corners(req.frame))
        return frame.norm.apply(req.corners @ frame.rotation.T)

    def _allowed(self, cand: dict, fit: float) -> float:
        """A candidate's ``fit`` as the choice reads it: a solid's (``solid_fits``) divided by the margin it is
        allowed against its own selection (``TriangleConfig.solid``), so that it keeps that allowance against
        the other candidates' selections too."""
        solid = cand.get("solid_fits", {}).get("faces_from") == "solid"
        return fit / self.triangle_config.solid if solid and self.triangle_config.solid else fit

    def _choose(self, req: Request, frame: Frame) -> dict:
        """The frame's candidate nearest its input surface (``support.weighed_fit``, a solid's with its margin:
        :meth:`_allowed`), turned back to the input's frame; raises the first candidate's GenerationError when
        none made a mesh."""
        n_cand, seed = req.candidates, req.params.seed
        best, fits, errors = None, [], []
        for k, cand in enumerate(frame.meshes):
            if isinstance(cand, GenerationError):
                errors.append(cand)
                fits.append(None)
                continue
            with stage("weighing", req.timings):  # choosing among candidates
                fit = weighed_fit(cand["vertices"], cand["faces"], frame.reference, seed) if n_cand > 1 else 0.0
            fits.append(round(float(fit), 6))
            if best is None or self._allowed(cand, fit) < self._allowed(best, best["fit"]):
                cells, positions, _ = frame.positions[k]
                best = {**cand, "fit": fit, "seed": seed + k, "k": k, "cells": cells, "positions": positions}
        if best is None:
            raise errors[0]
        best = self._with_missed(req, frame, self._with_quadrics(req, frame, best))
        evidence = best["evidence"].moved(frame.norm.invert(best["evidence"].points) @ frame.rotation)
        info = {"generated_vertices": best["generated_vertices"], "edges": best["edges"], "candidates": n_cand,
                "chosen_seed": best["seed"], "added_vertices": best["added_vertices"],
                "vertices_from": best["vertices_from"]}
        info.update({name: best[name] for name in ("missed_fits", "quadric_fits", "solid_fits") if name in best})
        if n_cand > 1:
            info["fits"] = fits  # per candidate: its weighed_fit in the unit cube, None if it made no mesh
        return {"vertices": frame.norm.invert(best["vertices"]) @ frame.rotation, "faces": best["faces"],
                "tokens": best["tokens"], "info": info, "rotation": frame.rotation, "evidence": evidence}
