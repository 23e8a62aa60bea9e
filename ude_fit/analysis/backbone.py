"""A data-derived backbone: the Hopf normal form's amplitude equation fitted to the points.

Near a Hopf point a self-excited system's limit-cycle amplitude r obeys

    r' = r (mu(V) + a r^2 + b r^4),    mu(V) = m (V - V_H),

(the normal form to fifth order, the growth rate linear in the airspeed; K. H. Lee, D.
Barton, L. Renson, MSSP 2023, fit this form to the same kind of wind-tunnel data). Its orbits
lie on one curve V = V_H + c1 s + c2 s^2 in s = r^2, so the model has exactly one Hopf point
(s = 0) and at most one fold (where dV/ds = 0): a model of the data with the qualitative
picture the physics allows and nothing else, and a yardstick for the UDE (reported beside
the mechanistic model). Fitting V(s) rather than r(V) keeps the problem linear and the
curve single-valued through the fold.

Stability: an orbit at s has Floquet exponent 2 s dg/ds with g = m (V - V(s)), i.e. it is
stable where m V'(s) > 0. The amplitudes alone do not fix the sign of m; the stability
labels do (the sign the most labelled points agree with; without labels, m > 0: the
equilibrium is stable below the Hopf point, as an aerofoil's is).

Uncertainty: the coefficients' covariance from the fit's residual variance (n - 3 degrees of
freedom) and its Jacobian, carried to the Hopf and fold airspeeds to first order.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from .._systems import system_kind
from .metrics_type import BranchErrors, PointError


@dataclass(frozen=True)
class HopfBackbone:
    """V(s) = hopf + c1 s + c2 s^2 in s = (r / r_scale)^2; ``m_sign`` the sign of dmu/dV."""
    hopf: float
    c1: float
    c2: float
    r_scale: float
    m_sign: int
    cov: np.ndarray             # (3, 3) covariance of (hopf, c1, c2); nan where unknown
    residual_std: float         # of the scaled orthogonal residuals (see fit_backbone)

    def airspeed(self, r) -> np.ndarray:
        """The airspeed of the orbit of amplitude ``r``."""
        s = (np.asarray(r, float) / self.r_scale) ** 2
        return self.hopf + self.c1 * s + self.c2 * s ** 2

    def stable(self, r) -> np.ndarray:
        """Whether the orbit of amplitude ``r`` (> 0) is stable."""
        s = (np.asarray(r, float) / self.r_scale) ** 2
        return self.m_sign * (self.c1 + 2 * self.c2 * s) > 0

    @property
    def fold_s(self) -> float | None:
        """s at the fold (dV/ds = 0 at s > 0), or None: the curve is monotone in s."""
        if self.c2 == 0:
            return None
        s = -self.c1 / (2 * self.c2)
        return float(s) if s > 0 else None

    @property
    def fold(self) -> float | None:
        """The fold's airspeed, or None."""
        s = self.fold_s
        return None if s is None else float(self.hopf + self.c1 * s + self.c2 * s ** 2)

    @property
    def fold_amplitude(self) -> float | None:
        s = self.fold_s
        return None if s is None else float(self.r_scale * np.sqrt(s))

    def hopf_std(self) -> float:
        return float(np.sqrt(self.cov[0, 0]))

    def fold_std(self) -> float | None:
        """First-order standard error of the fold airspeed: V_f = hopf - c1^2 / (4 c2)."""
        if self.fold_s is None:
            return None
        grad = np.array([1.0, -self.c1 / (2 * self.c2), self.c1 ** 2 / (4 * self.c2 ** 2)])
        return float(np.sqrt(grad @ self.cov @ grad))

    def orbits_at(self, V: float) -> list[tuple[float, bool]]:
        """(amplitude, stable) of every orbit at airspeed ``V``, smallest first."""
        roots = np.roots([self.c2, self.c1, self.hopf - V]) if self.c2 != 0 else (
            np.array([(V - self.hopf) / self.c1]) if self.c1 != 0 else np.array([]))
        s = np.sort([x.real for x in np.atleast_1d(roots)
                     if abs(x.imag) <= 1e-12 * (1 + abs(x.real)) and x.real > 0])
        r = self.r_scale * np.sqrt(s)
        return [(float(a), bool(self.stable(a))) for a in r]

    def branch(self, r_max: float, n: int = 200) -> dict:
        """Points of the curve from rest to ``r_max``: {"parameter", "amplitude", "stable"}."""
        r = np.linspace(0.0, r_max, n)
        return {"parameter": self.airspeed(r), "amplitude": r,
                "stable": self.stable(np.maximum(r, 1e-300 * self.r_scale))}

    def metrics(self, V, A, stable) -> BranchErrors:
        """Branch amplitude errors against measured points (the definitions of
        :mod:`ude_fit.analysis.metrics`: the orbit at the point's airspeed with its stability,
        nearest in amplitude, error over the largest measured amplitude; missed where none).
        The backbone has no trajectory, so the points have no trajectory error."""
        V, A = np.asarray(V, float), np.asarray(A, float)
        a_max = float(A.max())
        points = []
        for v, a, st in zip(V, A, stable):
            measured = dict(parameter=float(v), frequency=None, measured=float(a), stable=st)
            cands = [(r, s) for r, s in self.orbits_at(v) if st is None or s == st]
            if not cands:
                points.append(PointError(**measured))
                continue
            r, s = min(cands, key=lambda x: abs(x[0] - a))
            points.append(PointError(**measured, model=r, error=abs(r - a) / a_max,
                                     model_stable=s))
        return BranchErrors.of(points, a_max)

    def to_json(self) -> dict:
        return {"form": "r' = r (m (V - V_H) + a r^2 + b r^4): V = V_H + c1 s + c2 s^2, "
                        "s = (r / r_scale)^2",
                "hopf": self.hopf, "hopf_std": self.hopf_std(), "fold": self.fold,
                "fold_std": self.fold_std(), "fold_amplitude": self.fold_amplitude,
                "c1": self.c1, "c2": self.c2, "r_scale": self.r_scale,
                "growth_sign": self.m_sign, "residual_std": self.residual_std}


@dataclass(frozen=True)
class BackboneFit:
    """A backbone fitted to measured points, with its branch errors against them."""
    curve: HopfBackbone
    errors: BranchErrors

    def to_json(self) -> dict:
        """The curve and its headline figures (as metrics.json's ``backbone``)."""
        s = self.errors.summary
        return {**self.curve.to_json(), "branch_rms": s.branch_rms,
                "branch_max": s.branch_max, "missed": s.missed}


def fit_backbone(V, A, stable=None) -> HopfBackbone | None:
    """The backbone through measured orbits (airspeeds ``V``, amplitudes ``A`` > 0, stability
    True/False/None each); None for fewer than 4 orbits or fewer than 3 distinct amplitudes.

    Both the airspeed and the amplitude of a point are measured with error, and near the
    fold a small error in V is a large one in A, so the curve is fitted by orthogonal
    distance: each point has its own s_i on the curve, and the residuals are
    (V_i - V(s_i)) / span(V) and (A_i - r_scale sqrt(s_i)) / r_scale (each in units of the
    data's own extent, so nothing depends on the units or the rig). The start is linear
    least squares for V(s) at the measured s. Then the sign of the growth rate from the
    labels (see the module docstring)."""
    V, A = np.asarray(V, float), np.asarray(A, float)
    if V.shape != A.shape or V.ndim != 1:
        raise ValueError("V and A must be 1-d arrays of one length")
    if np.any(~np.isfinite(V)) or np.any(~np.isfinite(A)) or np.any(A <= 0):
        raise ValueError("amplitudes must be finite and positive, airspeeds finite")
    if V.size < 4 or np.unique(A).size < 3 or np.ptp(V) == 0:
        return None
    stable = [None] * V.size if stable is None else list(stable)
    r_scale, v_span = float(A.max()), float(np.ptp(V))
    u0 = A / r_scale
    X = np.stack([np.ones_like(u0), u0 ** 2, u0 ** 4], axis=1)
    start, *_ = np.linalg.lstsq(X, V, rcond=None)

    def residuals(x):
        c, u = x[:3], x[3:]
        s = u ** 2
        return np.concatenate([(V - (c[0] + c[1] * s + c[2] * s ** 2)) / v_span, u0 - u])

    sol = least_squares(residuals, np.concatenate([start, u0]), method="lm")
    coef, u = sol.x[:3], np.abs(sol.x[3:])
    dof = V.size - 3                       # 2n residuals, n + 3 unknowns
    var = float(sol.fun @ sol.fun / dof)
    cov = var * np.linalg.pinv(sol.jac.T @ sol.jac)[:3, :3]
    hopf, c1, c2 = (float(c) for c in coef)
    slope = c1 + 2 * c2 * u ** 2
    # the labelled points vote for the sign of m (stable where m V'(s) > 0)
    votes = sum((1 if st else -1) * np.sign(d) for st, d in zip(stable, slope)
                if st is not None)
    m_sign = -1 if votes < 0 else 1
    return HopfBackbone(hopf, c1, c2, r_scale, m_sign, cov, float(np.sqrt(var)))


def backbone_of(ds) -> HopfBackbone | None:
    """The backbone of a dataset of self-excited orbits (None for forced data, where the
    amplitude depends on the forcing, not on a growth rate). Orbits of zero amplitude (rest
    logged as a point) say nothing about the curve's shape and are left out of the fit."""
    if not system_kind(ds.system).autonomous:
        return None
    A = ds.amplitudes()
    keep = A > 0
    return fit_backbone(ds.parameters()[keep], A[keep],
                        [o.stable for o, k in zip(ds.orbits, keep) if k])
