"""The loop's time budget (`inseggan loop --minutes`): one figure the user gives, each stage's
share of it worked out as the run goes.

The loop's stages differ in what their time buys. The shape stage, the family choice and the
centre votes are elastic: fewer iterations or fewer candidates still give a model, a worse
one. The piles' simulation and the export are not cut (the piles' count sets what the centre
votes learn from). So before each elastic stage the time left is split over the stages still
to come in proportion to their weights (`WEIGHTS`), and the stage gets its share of it:

  shape    the shape stage's wall-clock limit (`TrainConfig.max_minutes`, at most as given);
  family   the candidates made and piled until their share is spent: a candidate whose
           expected time (the mean of those made) no longer fits is skipped, and the scale
           search takes no step past the grid's end beyond it (`family.choose`);
  centres  the centre votes' iterations: their share over the seconds one iteration takes,
           timed on this machine before the stage (`centres.step_seconds`), at most as given,
           at least `MIN_CENTRE_ITERATIONS`.

A stage that finishes early leaves its time to those after it. The weights are the stages'
shares of a default loop on a part with no recipe, measured on two cores (U-clips: shape
and sizing 5.6 min; T-pieces: family 19.4 with nine candidates and the bars' width search,
piles 4.6, centres 10.6, export 0.2; docs/experiments.md, 2026-12-07), with room for the
export's card. With a budget
of 0 nothing is cut.

A resumed run gets its budget anew from the moment it starts again: the stages it finished
cost nothing then, and the budget bounds the run's remaining work.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

DEFAULT_MINUTES = 45.0  # `inseggan loop --minutes`: a default loop took 36-41 minutes on
# two cores (docs/experiments.md), so the budget cuts it only on a slower or busier machine

# each stage's weight in the split of the time left (see the module's docstring)
WEIGHTS = {"shape": 0.13, "family": 0.47, "simulate": 0.11, "centres": 0.26, "export": 0.03}
ORDER = tuple(WEIGHTS)
MIN_CENTRE_ITERATIONS = 300  # a net of fewer has not settled (its validation mIoU still rising)
MARGIN = 0.9  # of a stage's share that iterations are planned to fill: validation and
# checkpoints take the rest


@dataclass
class Budget:
    """A run's deadline, `minutes` from its start (0: none), and what each stage was given."""

    minutes: float = 0.0
    stages: tuple[str, ...] = ORDER  # the stages the run has, in `ORDER`
    start: float = field(default_factory=time.monotonic)
    given: dict = field(default_factory=dict)  # stage -> seconds allotted
    cuts: list = field(default_factory=list)  # what the budget cut, in words

    def __post_init__(self):
        unknown = [s for s in self.stages if s not in WEIGHTS]
        if unknown:
            raise ValueError(f"stages {unknown} invalid; valid: {', '.join(WEIGHTS)}")
        if not (self.minutes == 0 or (math.isfinite(self.minutes) and self.minutes >= 5)):
            raise ValueError(f"minutes {self.minutes!r} invalid; valid: 0 (no time budget) or "
                             "5 and more (the loop's shortest run of a few hundred frames)")

    @property
    def bounded(self) -> bool:
        return self.minutes > 0

    def left(self) -> float:
        """Seconds to the deadline (inf without a budget; negative past it)."""
        if not self.bounded:
            return math.inf
        return self.minutes * 60 - (time.monotonic() - self.start)

    def share(self, stage: str) -> float:
        """Seconds for `stage`: the time left times its weight over the weights of it and the
        run's stages after it -> inf without a budget. Recorded in `given`."""
        if stage not in self.stages:
            raise ValueError(f"stage {stage!r} invalid; valid: {', '.join(self.stages)}")
        if not self.bounded:
            return math.inf
        rest = [s for s in self.stages if ORDER.index(s) >= ORDER.index(stage)]
        seconds = max(0.0, self.left()) * WEIGHTS[stage] / sum(WEIGHTS[s] for s in rest)
        self.given[stage] = round(seconds, 1)
        return seconds

    def cut(self, what: str) -> None:
        self.cuts.append(what)

    def record(self) -> dict:
        """The summary's and the card's account: the budget, each share, what was cut."""
        used = time.monotonic() - self.start
        return {"minutes": self.minutes, "used_minutes": round(used / 60, 1),
                "shares_minutes": {k: round(v / 60, 1) for k, v in self.given.items()},
                "cut": list(self.cuts),
                "over": bool(self.bounded and used > self.minutes * 60)}


def centre_iterations(asked: int, seconds: float, step: float) -> int:
    """The centre votes' iterations in `seconds` at `step` seconds each (`MARGIN` of it): at
    most `asked`, at least `MIN_CENTRE_ITERATIONS` (or `asked`, if fewer)."""
    if not math.isfinite(seconds):
        return asked
    fit = int(MARGIN * seconds / max(step, 1e-6))
    return max(min(asked, MIN_CENTRE_ITERATIONS), min(asked, fit))
