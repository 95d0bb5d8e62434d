"""Progress of one :meth:`fastmesh.pipeline.Pipeline.generate` call: the stage running and the overall fraction done.

A person watches it as a bar and a stage name, so it goes one way: the fraction never decreases and the stage
never goes back to one it has passed, and a stage that does not run (filtering, unless asked for) is never
named.  The pipeline runs each stage for every frame and candidate before the next stage (encode all, decode
all, enhancer for all, then faces), and tells this object which part of the stage it is in.
"""

from __future__ import annotations

from collections.abc import Callable

# The stages in the order they run, with the share of the progress bar each covers (decoding dominates).
# Faces and filtering run one candidate after the other: each candidate has its slice of their joint span.
STAGES = (("encode", 0.0, 0.03), ("vertices", 0.03, 0.80), ("enhancer", 0.80, 0.83), ("faces", 0.83, 0.90),
          ("filtering", 0.90, 1.0))
SPANS = {name: (lo, hi) for name, lo, hi in STAGES}
PER_CANDIDATE = ("faces", "filtering")


class Progress:
    """``callback(stage, fraction)`` made one-way (see the module).

    Parameters
    ----------
    callback : callable or None
        What the caller passed as ``progress``; None reports nowhere.
    filtering : bool
        Whether the filtering stage runs.  Without it the face stage covers filtering's share of the bar.
    """

    def __init__(self, callback: Callable[[str, float], None] | None, filtering: bool):
        self.callback = callback or (lambda stage, fraction: None)
        self.order = [name for name, _, _ in STAGES if filtering or name != "filtering"]
        lo, hi = SPANS[PER_CANDIDATE[0]]
        top = SPANS[PER_CANDIDATE[-1]][1]
        self.faces_share = (hi - lo) / (top - lo) if filtering else 1.0
        self.stage: str | None = None
        self.fraction = 0.0

    def fraction_of(self, stage: str, within: float, part: int = 0, parts: int = 1) -> float:
        """The overall fraction at ``within`` (0..1) of part ``part`` of ``parts`` of ``stage``."""
        within = min(max(float(within), 0.0), 1.0)
        if stage in PER_CANDIDATE:
            lo, hi = SPANS[PER_CANDIDATE[0]][0], SPANS[PER_CANDIDATE[-1]][1]
            a, b = (0.0, self.faces_share) if stage == "faces" else (self.faces_share, 1.0)
            x = (part + a + (b - a) * within) / parts
        else:
            lo, hi = SPANS[stage]
            x = (part + within) / parts
        return lo + (hi - lo) * x

    def __call__(self, stage: str, within: float = 0.0, part: int = 0, parts: int = 1) -> None:
        """Report ``stage`` at ``within`` of its part ``part`` of ``parts`` (a frame, a candidate).

        A stage before the one reported last (a later candidate's face pass after an earlier one's filtering)
        is reported as that one: the stage shown is the furthest reached.
        """
        fraction = max(self.fraction, self.fraction_of(stage, within, part, parts))
        if self.stage is not None and self.order.index(stage) < self.order.index(self.stage):
            stage = self.stage
        self.stage, self.fraction = stage, fraction
        self.callback(stage, fraction)

    def part(self, stage: str, part: int, parts: int) -> Callable[[float], None]:
        """``report(within)`` for part ``part`` of ``parts`` of ``stage``."""
        return lambda within: self(stage, within, part, parts)

    def done(self, stage: str = "faces") -> None:
        """The whole call done: the fraction 1, at the furthest stage reached (``stage`` when none was)."""
        self.stage = self.stage or stage
        self.fraction = 1.0
        self.callback(self.stage, 1.0)
