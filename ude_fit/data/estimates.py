"""What the measured points alone say about the diagram: the Hopf point the unstable orbits
extrapolate to, and the fold where the branch turns (rough; for reporting when no truth
is given, and for the penalties that need to know where the Hopf point lies); and how far
the points scatter about smooth branches, in amplitude and in the parameter."""

from __future__ import annotations

import numpy as np

from .orbit import OrbitDataset


def estimate_from_data(ds: OrbitDataset) -> dict:
    """Hopf and fold airspeeds estimated from the measured aerofoil points alone.

    Hopf: near a Hopf point the squared amplitude is linear in the airspeed, so a straight
    line through (V, A^2) of the smaller half of the unstable points, extrapolated to A = 0.
    Fold: the vertex of a parabola V(A) through the points around the smallest airspeed.
    Either is None where the data cannot support it. Rough: for reporting when no truth.
    """
    if not ds.kind.autonomous or len(ds.orbits) < 3:
        return {"hopf": None, "fold": None}
    V, A = ds.parameters(), ds.amplitudes()
    known = ds.known_stability()
    out = {"hopf": None, "fold": None}
    unst = np.nonzero(known & ~np.array([bool(o.stable) for o in ds.orbits]))[0]
    c = unstable_amplitude_line(V[unst], A[unst])
    if c is not None and c[0] != 0:
        out["hopf"] = float(-c[1] / c[0])
    order = np.argsort(V)[:min(5, len(V))]
    if np.ptp(A[order]) > 0 and len(order) >= 3:
        c = np.polyfit(A[order], V[order], 2)
        if c[0] > 0:
            a_star = -c[1] / (2 * c[0])
            if A[order].min() <= a_star <= A[order].max():
                out["fold"] = float(np.polyval(c, a_star))
    return out


def unstable_amplitude_line(V, A):
    """(slope, intercept) of a straight line through (V, A^2) of the smaller half of the
    given unstable orbits (near a Hopf point A^2 is linear in V); None for fewer than two
    orbits or all at one airspeed."""
    V, A = np.asarray(V, float), np.asarray(A, float)
    if V.size < 2:
        return None
    idx = np.argsort(A)[:max(2, V.size // 2 + 1)]
    if np.ptp(V[idx]) == 0:
        return None
    return np.polyfit(V[idx], A[idx] ** 2, 1)


def data_scatter(ds: OrbitDataset) -> float:
    """How far the measured points themselves lie from smooth branches: the residual
    standard deviation of a quadratic in the parameter through each stability class (of 4
    or more points; per frequency for the oscillator), over the largest amplitude. No fit
    can be asked to be closer to the data than this.

    The residuals' plain RMS would underestimate the scatter: each quadratic is fitted to
    the very points it is judged on and takes 3 of their degrees of freedom (with 4 points,
    3 of 4), so the sum of squares is divided by the points left over, as the textbook
    unbiased estimate of a regression's residual variance does."""
    A, P = ds.amplitudes(), ds.parameters()
    groups = [np.ones(len(ds), bool)] if ds.kind.autonomous else [
        np.round(ds.frequencies(), 6) == f for f in ds.frequencies_group()]
    return _pooled_quadratic_sd(P, A, [g & m for g in groups for m in _stability_classes(ds)]
                                ) / float(A.max())


def parameter_scatter(ds: OrbitDataset) -> float:
    """The parameter's residual standard deviation about a quadratic in the amplitude
    through each stability class of 4 or more points, pooled with their degrees of freedom
    (0 where there is no such class)."""
    return _pooled_quadratic_sd(ds.amplitudes(), ds.parameters(), _stability_classes(ds))


def _stability_classes(ds: OrbitDataset) -> list[np.ndarray]:
    """Masks of the stable and of the unstable points (points of unknown stability are in
    neither)."""
    return [np.array([o.stable is label for o in ds.orbits]) for label in (True, False)]


def _pooled_quadratic_sd(x: np.ndarray, y: np.ndarray, masks: list[np.ndarray]) -> float:
    """The residual standard deviation of ``y`` about a quadratic in ``x`` fitted within
    each mask of 4 or more points spread in ``x``, pooled over the masks with their
    degrees of freedom (0 where no mask qualifies)."""
    ss, dof = 0.0, 0
    for m in masks:
        if m.sum() >= 4 and np.ptp(x[m]) > 0:
            c = np.polyfit(x[m], y[m], 2)
            ss += float(np.sum(np.square(y[m] - np.polyval(c, x[m]))))
            dof += int(m.sum()) - 3
    return float(np.sqrt(ss / dof)) if dof > 0 else 0.0
