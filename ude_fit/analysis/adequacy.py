"""Adequacy of a fitted start (the paper found single trainings often land in poor local
minima; see :mod:`ude_fit.fitting`): fold counts, the checks a start must pass, and the
judgement of every start against the best credible one (the data's own scatter, which they
read, is :func:`ude_fit.data.estimates.data_scatter`)."""

from __future__ import annotations

import numpy as np

from ..data.orbit import OrbitDataset
from ..training.options import FitOptions
from .metrics_type import ModelMetrics


def error_bar(mech_m: ModelMetrics, baseline_rms: float | None = None
              ) -> tuple[float | None, str | None]:
    """The branch error a credible start must be below, and which model sets it: the
    mechanistic model's; where that model misses every point (no error to beat, and
    without a bar the best credible start would be adequate however far it lies from the
    points), ``baseline_rms``, the points' own backbone's; else none."""
    if mech_m.summary.branch_rms is not None:
        return mech_m.summary.branch_rms, "mechanistic"
    if baseline_rms is not None:
        return baseline_rms, "backbone"
    return None, None


def _credible(m: ModelMetrics | None, mech_m: ModelMetrics, fold_required: bool = False,
              baseline_rms: float | None = None) -> bool:
    """Every check of adequacy but the comparison with the other starts: nothing missed,
    no more folds than allowed (and one at least where the data needs one), below the
    mechanistic model's error (at every frequency); where the mechanistic model has no
    error to beat (it misses every point), below ``baseline_rms`` (the data's backbone)."""
    if m is None or m.summary.branch_rms is None or m.summary.missed > 0:
        return False
    # stable and unstable orbits of a self-excited system meet at a fold; a diagram whose
    # stable and unstable branches run side by side out of the window without one claims
    # bistability at every lower airspeed
    if fold_required and m.fold_count == 0:
        return False
    # qualitatively the mechanistic model's diagram: at most one extra fold per branch
    # family (a network that snakes through the points is not a model of them)
    if m.fold_count > mech_m.fold_count + mech_m.families:
        return False
    bar, _ = error_bar(mech_m, baseline_rms)
    if bar is not None and m.summary.branch_rms >= bar:
        return False
    # oscillator: better than the mechanistic model at every frequency, not just overall
    mine = m.per_frequency or {}
    for f, v in (mech_m.per_frequency or {}).items():
        rms = mine[f].branch_rms if f in mine else None
        if v.branch_rms is not None and (rms is None or rms >= v.branch_rms):
            return False
    return True


def _is_adequate(m, best_rms, mech_m, opts, scatter: float = 0.0,
                 fold_required: bool = False, baseline_rms: float | None = None) -> bool:
    """Credible, and within ``adequacy_factor`` of the best credible start's error (or
    under the floor, or under the data's own scatter)."""
    return _credible(m, mech_m, fold_required, baseline_rms) and m.summary.branch_rms <= max(
        opts.adequacy_factor * best_rms, opts.adequacy_floor, scatter)


def judge_starts(start_metrics: list[ModelMetrics | None], mech_m: ModelMetrics,
                 opts: FitOptions, scatter: float = 0.0,
                 fold_required: bool = False,
                 baseline_rms: float | None = None) -> list[bool]:
    """Adequacy of each start (None for a dropped one). The reference for "within a factor
    of the best" is the best start that is itself credible: one that snakes through every
    point (folds the data does not show) fits closer than a model of the physics should,
    and must not set the bar."""
    best_rms = min((m.summary.branch_rms for m in start_metrics
                    if _credible(m, mech_m, fold_required, baseline_rms)), default=np.inf)
    return [m is not None and _is_adequate(m, best_rms, mech_m, opts, scatter, fold_required,
                                           baseline_rms)
            for m in start_metrics]


def needs_fold(ds: OrbitDataset) -> bool:
    """Aerofoil data with stable and unstable orbits: the branch from the Hopf point turns
    at a fold to become the stable one, so a diagram needs one."""
    return ds.kind.autonomous and any(o.stable is True for o in ds) and any(
        o.stable is False for o in ds)
