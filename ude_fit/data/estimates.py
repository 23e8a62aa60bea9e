"""What the measured points alone say about the diagram: the Hopf point the unstable orbits
extrapolate to, and the fold where the branch turns (rough; for reporting when no truth
is given, and for the penalties that need to know where the Hopf point lies)."""

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
