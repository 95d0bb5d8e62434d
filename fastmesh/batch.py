"""Several generation jobs through one pipeline at once, their vertex decoding batched.

:meth:`fastmesh.pipeline.Pipeline.steps` runs one job as a generator that stops where it needs the vertex
decoder: it yields a :class:`DecodeRequest` (its candidates' prefixes, evidence, sampling settings and seeds)
and is sent back one token sequence per candidate.  A :class:`Batch` holds several such jobs.  Each
:meth:`Batch.round` decodes every pending request, those of the same sampling settings as one batch of rows
(``models.generate``: each row keeps its own seed, evidence and grammar state, so it is the sequence it gives
alone), then runs each job on, on its own, to its next request or its end.  A job added between two rounds joins
the next one: continuous batching at the granularity of a decode round (a worker adds a job whenever one ends).

What each job sees is what it sees alone: its progress (its own rows' vertex counts), its cancellation (its rows
stop, the others' go on), its timings (``vertices`` from its request to its rows, the round's wait included).  A
request whose batched decoding raises is decoded again alone, so one job's error stays that job's; an error
``fatal`` says leaves the process unusable (a CUDA error) stops the batch instead (:attr:`Batch.failed`).
"""

from __future__ import annotations

from collections.abc import Callable, Generator, Hashable
from dataclasses import dataclass, replace

import torch

from .models.generate import Cancelled, StackedEvidence, generate
from .params import SamplingConfig

Steps = Generator["DecodeRequest", list[torch.Tensor], object]


@dataclass
class DecodeRequest:
    """One job's vertex decoding: its n candidates as rows.

    Attributes
    ----------
    prefix : (n, M, dim) float tensor, the decoder's condition of each candidate
    evidence : list of n ``Evidence`` (one per candidate, each computed alone), or None
    sampling : the job's ``SamplingConfig`` (its ``seed`` is replaced by ``seeds``)
    seeds : n generator seeds, one per candidate
    progress : called with the most vertices any of the job's rows has decoded so far
    should_cancel : polled while decoding; True stops the job's rows
    solo : decode these rows in no batch but their own (a job that met a device error before)
    """

    prefix: torch.Tensor
    evidence: list | None
    sampling: SamplingConfig
    seeds: list[int]
    progress: Callable[[int], None]
    should_cancel: Callable[[], bool] | None
    solo: bool = False

    @property
    def rows(self) -> int:
        return len(self.seeds)


def decode(decoder, requests: list[DecodeRequest], fatal: Callable[[BaseException], bool] | None = None,
           progress_every: int = 16) -> list[list[torch.Tensor] | BaseException | None]:
    """Decode ``requests`` together: those of equal sampling settings (seeds aside) as one batch of rows.

    Returns per request its sequences (BOS ... EOS, one per row), :class:`Cancelled` when it asked to stop, the
    exception its decoding raised alone, or None when an earlier group raised an error ``fatal`` calls fatal
    (nothing after it is decoded).
    """
    groups: dict[tuple, list[int]] = {}
    for i, r in enumerate(requests):
        groups.setdefault((replace(r.sampling, seed=0), i if r.solo else -1), []).append(i)
    out: list = [None] * len(requests)
    for index in groups.values():
        try:
            got = _decode_group(decoder, [requests[i] for i in index], progress_every)
        except Exception as e:  # noqa: BLE001 - whatever it is, it is the outcome of these requests
            if (fatal is not None and fatal(e)) or len(index) == 1:
                got = [e] * len(index)
            else:  # one request's error must not be the others': each alone
                got = [_alone(decoder, requests[i], progress_every) for i in index]
        for i, g in zip(index, got, strict=True):
            out[i] = g
        if fatal is not None and any(isinstance(g, BaseException) and fatal(g) for g in got):
            break
    return out


def _alone(decoder, request: DecodeRequest, progress_every: int) -> list[torch.Tensor] | BaseException:
    try:
        return _decode_group(decoder, [request], progress_every)[0]
    except Exception as e:  # noqa: BLE001
        return e


def _decode_group(decoder, requests: list[DecodeRequest], progress_every: int) -> list:
    """One ``generate`` call over the rows of ``requests`` (equal sampling settings); per request its sequences
    or :class:`Cancelled`.  Each request's ``vertices`` timing gets the call's seconds."""
    spans, at = [], 0
    for r in requests:
        spans.append((at, at + r.rows))
        at += r.rows
    evidence = [e for r in requests for e in (r.evidence or [])]
    ev = None if not evidence else evidence[0] if len(evidence) == 1 else StackedEvidence(evidence)
    cancelled: set[int] = set()

    def control(step: int, n_vert: list[int]) -> list[bool]:
        """Each request's progress from its own rows, and its rows stopped once it asks to stop."""
        flags = []
        for j, (r, (lo, hi)) in enumerate(zip(requests, spans, strict=True)):
            if j not in cancelled and r.should_cancel is not None and r.should_cancel():
                cancelled.add(j)
            if j not in cancelled:
                r.progress(max(n_vert[lo:hi]))
            flags += [j in cancelled] * (hi - lo)
        return flags

    seqs = generate(decoder, torch.cat([r.prefix for r in requests]), requests[0].sampling, evidence=ev,
                    seeds=[s for r in requests for s in r.seeds], rows=control, progress_every=progress_every)
    return [Cancelled("generation cancelled") if j in cancelled else seqs[lo:hi]
            for j, (lo, hi) in enumerate(spans)]


class Batch:
    """Jobs (:meth:`fastmesh.pipeline.Pipeline.steps` generators) run together, their decoding batched.

    Parameters
    ----------
    pipe : the :class:`fastmesh.pipeline.Pipeline` whose ``steps`` the jobs are: its decoder decodes them, with
        its threads of the vertex stage
    fatal : an error after which nothing more may run in this process (a CUDA error): it sets :attr:`failed`
        and is the outcome of the job that raised it (of every job in the decoding that raised it: which row
        caused a device error cannot be told); the batch then runs nothing more (:meth:`close` drops the rest)
    """

    def __init__(self, pipe, fatal: Callable[[BaseException], bool] | None = None):
        self.pipe, self.fatal = pipe, fatal
        self.waiting: dict[Hashable, tuple[Steps, DecodeRequest]] = {}  # jobs at a decode request, in order
        self.done: dict[Hashable, object] = {}  # finished jobs: their result or exception, until pop_done
        self.failed: BaseException | None = None

    def __len__(self) -> int:
        """Jobs still running (each waits for its next decoding)."""
        return len(self.waiting)

    def add(self, key: Hashable, steps: Steps, solo: bool = False) -> None:
        """Start job ``key``: run it to its first decode request (it joins the next round) or its end."""
        if key in self.waiting or key in self.done:
            raise ValueError(f"job {key!r} is in the batch already")
        self._advance(key, steps, solo, lambda: next(steps))

    def round(self) -> None:
        """Decode every waiting request together, then run each job on to its next request or its end."""
        if self.failed is not None or not self.waiting:
            return
        items = list(self.waiting.items())
        with self.pipe.threads_for("vertices"):
            got = decode(self.pipe.decoder, [req for _, (_, req) in items], self.fatal)
        fatal = [(key, e) for (key, _), e in zip(items, got, strict=True) if self._is_fatal(e)]
        if fatal:  # every job whose rows were in the failed decoding has that error; nothing more runs
            self.failed = fatal[0][1]
            for key, e in fatal:
                self.waiting.pop(key)[0].close()
                self.done[key] = e
            return
        for (key, (steps, req)), seqs in zip(items, got, strict=True):
            del self.waiting[key]
            if isinstance(seqs, BaseException):
                self._advance(key, steps, req.solo, lambda s=steps, e=seqs: s.throw(e))
            else:
                self._advance(key, steps, req.solo, lambda s=steps, q=seqs: s.send(q))
            if self.failed is not None:  # the process is unusable: nothing more runs in it
                return

    def _is_fatal(self, outcome) -> bool:
        return isinstance(outcome, BaseException) and self.fatal is not None and self.fatal(outcome)

    def pop_done(self) -> dict[Hashable, object]:
        """The jobs finished since the last call: key -> result, or the exception the job raised."""
        done, self.done = self.done, {}
        return done

    def close(self) -> list[Hashable]:
        """Abandon the jobs still running (after :attr:`failed`, or a shutdown); returns their keys."""
        keys = list(self.waiting)
        for steps, _ in self.waiting.values():
            steps.close()
        self.waiting.clear()
        return keys

    def _advance(self, key: Hashable, steps: Steps, solo: bool, move: Callable[[], DecodeRequest]) -> None:
        try:
            req = move()
        except StopIteration as end:
            self.done[key] = end.value
        except Exception as e:  # noqa: BLE001 - the job's own outcome (Cancelled, GenerationError, ...)
            self.done[key] = e
            if self._is_fatal(e):
                self.failed = e
        else:
            req.solo = solo
            self.waiting[key] = (steps, req)
