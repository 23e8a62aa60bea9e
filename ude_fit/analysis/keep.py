"""Which start a fit keeps.

Every adequate start reproduces the measured orbits (:mod:`.adequacy`: nothing missed, no
fold the data does not show, an error the data's scatter and the other starts allow). They
differ most where the data is silent: the Hopf point beyond the highest orbit, the fold
below the lowest, a forced branch's folds outside the measured forcing levels. There each
start is an independent extrapolation, and the start with the smallest branch error is
only the one that fits the points (and their noise) closest: its network may be the one
that bent furthest. So among three or more adequate starts the kept one is their *medoid*:
the start whose landmarks (:meth:`ModelMetrics.landmarks`: its Hopf and fold locations
outside the measured parameter range of their branch family) lie nearest the others',
summed over the other adequate starts. Where the measured orbits bracket every landmark (an
oscillator campaign across its S-curves) there is nothing the data leaves open, and the
smallest branch error decides; it does so too with fewer than three adequate starts (two
cannot outvote each other) and between equally central starts. With no adequate start, the
one with the fewest missed points and then the smallest error is kept (the fit says it is
not adequate).

Before the medoid or the smallest error decides, the adequate starts are narrowed to those
with the fewest folds. The adequacy check allows the mechanistic model's folds plus one
per branch family, so that a network may add the fold the data needs where the
mechanistic model has none (lee2020: no orbit at all); where the mechanistic model has a
fold of its own, a start may then add a second one the data does not show. On points that
scatter about their branches (a tunnel reading's error, a control left slightly invasive)
such starts are common and fit the points closest: the network bends through the scatter.
Held-out wind-tunnel files of the benchmark's `narrow` and `soft` rigs so scattered
(docs/experiments.md, sixty-ninth session) kept a start with two folds where starts with
one were adequate. Of two adequate diagrams the one with fewer turns is the one the data
asks for.

A cut at the data's scatter (only starts closer to the points than their own scatter in
the pool) was the first form: a correct model's branch error is about the scatter, and
above it as often as below, so the cut took out good starts.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from .metrics_type import ModelMetrics

# the fewest starts a consensus is taken over: with two, each is as near the other
CONSENSUS_STARTS = 3


@dataclass(frozen=True)
class KeptStart:
    """The kept start (its number, None when no start completed), the rule that chose it
    ("consensus", "smallest error", "not adequate" or "none"), the starts the consensus
    was taken over, the landmarks compared, each of those starts' summed distance to
    the others (in the landmarks' unit), and, where adequate starts with more folds were
    left out, the fold count the kept one was chosen among and the starts left out."""
    start: int | None
    rule: str
    pool: tuple[int, ...] = ()
    landmarks: tuple[str, ...] = ()
    distance: dict[int, float] = field(default_factory=dict)
    folds: int | None = None
    more_folds: tuple[int, ...] = ()

    RULES = ("consensus", "smallest error", "not adequate", "none")

    def __post_init__(self):
        if self.rule not in self.RULES:
            raise ValueError(f"rule must be one of {', '.join(self.RULES)}, not {self.rule!r}")
        if (self.start is None) != (self.rule == "none"):
            raise ValueError("a start is kept exactly when the rule is not 'none'")
        if self.rule == "consensus" and (len(self.pool) < CONSENSUS_STARTS
                                         or self.start not in self.pool
                                         or not self.landmarks):
            raise ValueError(f"a consensus needs {CONSENSUS_STARTS} or more starts, the "
                             "kept one among them, and a landmark to compare")
        if self.more_folds and (self.folds is None or self.start in self.more_folds):
            raise ValueError("starts left out for their folds need the fold count kept, "
                             "and the kept start is not among them")

    def to_json(self) -> dict:
        return {"start": self.start, "rule": self.rule, "pool": list(self.pool),
                "landmarks": list(self.landmarks),
                "distance": {str(k): v for k, v in self.distance.items()},
                "folds": self.folds, "more_folds": list(self.more_folds)}

    @classmethod
    def from_json(cls, d: dict) -> KeptStart:
        # files written before the fold count was part of the rule have neither key
        return cls(d["start"], d["rule"], tuple(d["pool"]), tuple(d["landmarks"]),
                   {int(k): float(v) for k, v in d["distance"].items()},
                   d.get("folds"), tuple(d.get("more_folds", ())))

    def describe(self) -> str:
        """One or two sentences for the report."""
        left_out = "" if not self.more_folds else (
            f" Adequate starts with more than {self.folds} fold"
            f"{'' if self.folds == 1 else 's'} (starts {', '.join(map(str, self.more_folds))})"
            " were left out: their diagrams turn where the data shows no turn.")
        if self.rule == "consensus":
            return (f"Kept: the medoid of the {len(self.pool)} adequate starts (starts "
                    f"{', '.join(map(str, self.pool))}) by their "
                    f"{' and '.join(self.landmarks)} (outside the measured range, where the "
                    "data does not pin them): the start whose locations lie nearest the "
                    "others'." + left_out)
        if self.rule == "smallest error":
            return ("Kept: the adequate start with the smallest branch error"
                    + (f" among those with {self.folds} fold"
                       f"{'' if self.folds == 1 else 's'}." if self.more_folds else ".")
                    + left_out)
        if self.rule == "not adequate":
            return ("No start is adequate; kept: the one with the fewest missed points, then "
                    "the smallest branch error.")
        return "No start completed."


def _error(m: ModelMetrics) -> float:
    # a completed start judged under the control may close no orbit at all: no error
    return np.inf if m.summary.branch_rms is None else m.summary.branch_rms


def choose_kept(starts: Sequence, spans: Mapping[str | None, tuple[float, float]]
                ) -> KeptStart:
    """The kept start among ``starts`` (records with ``start``, ``completed``, ``adequate``
    and ``judged``, the figures the start is judged by: its diagram's, or with the control
    as an input those under it, :func:`.controlled.judged`), ``spans`` being the measured
    parameter range of each branch family
    (:meth:`ude_fit.data.orbit.OrbitDataset.parameter_spans`)."""
    done = [s for s in starts if s.completed]
    if not done:
        return KeptStart(None, "none")
    adequate = sorted((s for s in done if s.adequate), key=lambda s: _error(s.judged))
    if not adequate:
        best = min(done, key=lambda s: (s.judged.summary.missed, _error(s.judged)))
        return KeptStart(best.start, "not adequate")
    fewest = min(s.judged.fold_count for s in adequate)
    more = tuple(sorted(s.start for s in adequate if s.judged.fold_count > fewest))
    adequate = [s for s in adequate if s.judged.fold_count == fewest]
    folds = fewest if more else None
    marks = [s.judged.landmarks(spans) for s in adequate]
    # the landmarks every adequate start has, in the first one's order
    names = tuple(n for n in marks[0] if all(n in m for m in marks[1:]))
    if len(adequate) < CONSENSUS_STARTS or not names:
        return KeptStart(adequate[0].start, "smallest error", folds=folds, more_folds=more)
    L = np.array([[m[n] for n in names] for m in marks])
    total = np.abs(L[:, None, :] - L[None, :, :]).sum(axis=(1, 2))
    # the first of the smallest sums: ``adequate`` is in order of branch error
    kept = adequate[int(np.argmin(total))]
    return KeptStart(kept.start, "consensus", tuple(sorted(s.start for s in adequate)), names,
                     {s.start: float(d) for s, d in sorted(zip(adequate, total),
                                                           key=lambda sd: sd[0].start)},
                     folds, more)
