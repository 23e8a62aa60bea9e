"""Guide rounds (``--guide-rounds R``; 2 by default for the aerofoil's network): a start
whose traced diagram breaks the adequacy check's picture of the data (more folds than it
allows, or a measured point with no orbit of its stability) is trained on with the one-fold
curve's guide orbits (:mod:`ude_fit.training.guides`), and traced again.

Both defects are the correction's freedom where the data is silent: a fold between or
above the measured orbits, or a branch that loses its stability between two orbits
measured with the same one (a secondary bifurcation the data does not show: lee2020 seed
0's third start, 2026-12-02, whose stable branch lost stability over 21.6-22.4 m/s and
so missed the stable orbit at 22.4).

Guides trained on from the start (``--guide-orbits``) pull every fit towards a curve a
few per cent from the points, and cost the simulated campaigns' fits most of their
accuracy (docs/fitting.md). A round is run only where the trained start breaks the
picture the rule asks for, as the constraint rounds run only where a condition is broken:
a start whose diagram already has it is left exactly as it was. The guides of a round
reach over the whole amplitude window the diagram is traced and judged in (a branch that
turns back above the guides' top would still count), where no measured orbit is near
(:func:`round_guides`). Each round trains from the last round's weights at the guides'
weight, three times the last round's, until the start has a model within the rule or
``R`` rounds have run. The start keeps the model nearest the rule among those that
miss no more measured points than the trained one (the earliest of equals: the least
guided).
"""

from __future__ import annotations

from dataclasses import dataclass

from .data.one_fold import OneFoldCurve, fit_one_fold
from .data.orbit import OrbitDataset
from .models.ude import UDE
from .training.guides import guide_orbits, with_guides
from .training.identify import TrainingData
from .training.optimise import Diverged
from .training.options import FitOptions
from .training.penalties import PENALTIES
from .training.rounds import broken_constraints
from .training.train import train_on

# guide orbits per round, evenly spaced over the window: about one per tenth of it
ROUND_GUIDES = 12
# each round's guide weight over the last's (the constraint rounds' escalation is tenfold;
# a guide asks for a whole orbit, so a gentler step)
WEIGHT_STEP = 3.0


@dataclass(frozen=True)
class GuideRound:
    """One round: the guides' weight, what the traced diagram showed after it, and the
    constraint conditions its model breaks (by option name)."""
    weight: float
    folds: int
    missed: int
    branch_rms: float | None
    loss: float
    broken: tuple[str, ...] = ()

    def to_json(self) -> dict:
        return {"weight": self.weight, "folds": self.folds, "missed": self.missed,
                "branch_rms": self.branch_rms, "loss": self.loss,
                "constraints_broken": list(self.broken)}


@dataclass(frozen=True)
class DiagramRule:
    """The adequacy check's picture of the data (:func:`ude_fit.analysis.adequacy._credible`):
    an orbit of its stability at every measured point, and at most ``allowed`` folds. (Its
    other fold condition, one at least where the data has stable and unstable orbits, is
    not a round's business: no round was measured to add one, and on a few points in a
    narrow window a start without one is common and costly to retrain.)"""
    allowed: int

    def excess(self, m) -> int:
        """How far ``m``'s diagram is from the rule: its folds beyond those allowed and its
        missed points."""
        return max(m.fold_count - self.allowed, 0) + m.summary.missed


@dataclass(frozen=True)
class GuideRepair:
    """A start's guide rounds: its folds and missed points before them, the rule, every
    round, the model kept (0: the trained one, k: round k's), why the rounds ended early,
    if they did, and the constraint conditions the trained model broke."""
    folds_before: int
    missed_before: int
    rule: DiagramRule
    rounds: tuple[GuideRound, ...]
    kept: int
    stop: str | None = None
    broken_before: tuple[str, ...] = ()

    @property
    def kept_broken(self) -> tuple[str, ...]:
        """The conditions the kept model breaks."""
        return self.rounds[self.kept - 1].broken if self.kept else self.broken_before

    def to_json(self) -> dict:
        return {"folds_before": self.folds_before, "missed_before": self.missed_before,
                "folds_allowed": self.rule.allowed,
                "rounds": [r.to_json() for r in self.rounds], "kept_round": self.kept,
                "stop": self.stop, "constraints_broken_before": list(self.broken_before)}


class GuideRounds:
    """The guide rounds of a fit (``opts.guide_rounds``): which starts break the adequacy
    rule's picture (more folds than the mechanistic model's count plus one per family, or a
    measured point missed), and the rounds for them; the one-fold curve is fitted once, at
    the first start that needs it. ``evaluate(model)`` traces a model and judges it against
    the data; ``say`` is the fit's progress callback."""

    def __init__(self, ds, data, mech_m, opts, evaluate, say, verbose):
        self.ds, self.data, self.opts, self.evaluate = ds, data, opts, evaluate
        self.rule = DiagramRule(mech_m.fold_count + mech_m.families)
        self.say, self.verbose = say, verbose
        self._guides = None

    def needed(self, m) -> bool:
        return bool(self.opts.guide_rounds) and self.rule.excess(m) > 0

    def run(self, start: int, model, diag, m, info):
        if self._guides is None:
            curve = fit_one_fold(self.ds, self.ds.kind.amplitude_window)
            if curve is None:
                return model, diag, m, GuideRepair(
                    m.fold_count, m.summary.missed, self.rule, (), 0,
                    "no one-fold curve: the data has no stable and unstable points")
            self._guides = round_guides(self.ds, curve)
        return repair_start(model, m, diag, data=self.data, guides=self._guides,
                            opts=self.opts, rule=self.rule,
                            constraint_weights=constraint_weights(info),
                            evaluate=self.evaluate,
                            progress=(lambda **kw: self.say(event="train", start=start, **kw))
                            if self.verbose else None)


def round_guides(ds: OrbitDataset, curve: OneFoldCurve) -> OrbitDataset:
    """The guide orbits every round trains on: :data:`ROUND_GUIDES` evenly spaced over the
    diagram's whole amplitude window, less those within half a step of a measured orbit.
    Where the data speaks a guide would only contradict it (the curve is a few per cent
    from the points, and its Hopf point is an extrapolation below the smallest orbit);
    the guides are for where it is silent."""
    grid = guide_orbits(ds, curve, ROUND_GUIDES, top=ds.kind.amplitude_window)
    half_step = 0.5 * (grid.orbits[1].amplitude - grid.orbits[0].amplitude)
    measured = [o.amplitude for o in ds if o.stable is not None]
    kept = tuple(g for g in grid
                 if min(abs(g.amplitude - a) for a in measured) > half_step)
    return OrbitDataset(grid.system, kept, tuple(g.source for g in kept))


def repair_start(model: UDE, metrics, diagram, *, data: TrainingData, guides: OrbitDataset,
                 opts: FitOptions, rule: DiagramRule, constraint_weights: dict, evaluate,
                 progress=None):
    """Guide rounds for one trained start whose diagram breaks ``rule``.

    ``evaluate(model)`` traces a model and judges it against the data: (diagram, metrics).
    ``constraint_weights``: the constraint rounds' final weights, by option name (the
    conditions stay at them; one never broken in training weighs 0, so every round's model
    is checked against them all and what it breaks is recorded). Returns (model, diagram,
    metrics, :class:`GuideRepair`) of the model kept."""
    before = metrics.fold_count, metrics.summary.missed
    broken_before = broken_constraints(model, data, opts.train)
    best = (metrics, 0, model, diagram)
    rounds, stop = [], None
    weight = opts.guide_weight
    current = model
    for k in range(1, opts.guide_rounds + 1):
        guided = with_guides(data, guides, model.mech, weight)
        try:
            current, loss = train_on(current, guided, cfg=opts.train,
                                     constraint_weights=constraint_weights,
                                     progress=progress, stage=f"guides, round {k}")
        except Diverged as err:
            stop = f"round {k} undone ({err})"
            break
        diag, m = evaluate(current)
        broken = broken_constraints(current, data, opts.train)
        rounds.append(GuideRound(weight, m.fold_count, m.summary.missed,
                                 m.summary.branch_rms, loss, broken))
        if _better(m, best[0], rule):
            best = (m, k, current, diag)
        if rule.excess(best[0]) == 0:
            break
        weight *= WEIGHT_STEP
    metrics, kept, model, diagram = best
    return model, diagram, metrics, GuideRepair(*before, rule, tuple(rounds), kept, stop,
                                                broken_before)


def _better(m, than, rule: DiagramRule) -> bool:
    """A round's model replaces the start's best so far where it is nearer the rule and
    misses no more points: a fold taken away at the price of a measured orbit is no
    repair. (The constraint conditions a round breaks are reported, not judged here: they
    are the training's means to the data's picture, with tolerances far inside what a
    diagram shows, and refusing such rounds cost 3 adequate starts of 25 on lee2020.)"""
    return (rule.excess(m) < rule.excess(than)
            and m.summary.missed <= than.summary.missed)


def constraint_weights(info: dict) -> dict:
    """The constraint rounds' final weights from a start's training info, by option name."""
    return {p.option: info[f"{p.option}_weight"] for p in PENALTIES
            if f"{p.option}_weight" in info}
