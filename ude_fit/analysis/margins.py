"""Stability margins from the data (``--backbone-margins``, experimental): how stable or
unstable each labelled orbit is, as the points' Hopf normal-form backbone predicts it.

The periodic training asks each labelled orbit's stability indicator (the product of
1 - mu over its non-trivial Floquet multipliers mu: ``stability_indicator``) to lie beyond
a margin on its labelled side. A constant margin is a dimensionless number no rig fixes;
the thirty-third session found it decides how many starts succeed (docs/experiments.md).
The backbone (:mod:`ude_fit.analysis.backbone`) predicts it. On V = V(s), s ~ r^2, the
amplitude's Floquet exponent is

    lambda = 2 s dg/ds = -2 s m V'(s),       g = m (V - V(s)),

with m the equilibrium's growth-rate slope at the backbone's Hopf point, taken from the
mechanistic model (identified from the same data). The orbit's amplitude multiplier is
exp(lambda T); its other multipliers are taken as the mechanistic linearisation's at the
orbit's airspeed, exp(sigma_k T) for every eigenvalue but the critical pair (which becomes
the trivial multiplier and the amplitude's).

The slope V'(s) is the one the data supports under two forms of the curve, each moved one
standard error towards zero, whichever is nearer zero: the backbone's quadratic
c1 + 2 c2 s, and the straight line V = a + b s through the orbits of the same stability
(the branch's own mean slope, its standard error from the line's residuals). A parabola's
slopes are the same size either side of its vertex; a measured branch's need not be: on the
rig's noise-free truth (orbits at 17-23.6 m/s) the quadratic through both branches gives the
large stable orbits 5-7 times the truth's slope, and alone it asked them for
amplitude factors of 0.96-1.0 where the truth's are 0.54-0.57 (docs/experiments.md,
thirty-seventh session). A branch of fewer than three labelled orbits has no line, and the
quadratic alone holds there.

Where either form's stability disagrees with the label, or its slope is within one standard
error of zero, there is no prediction and the configured constant margin holds; it is also
the least margin. Nor is there one for each branch's orbit nearest the backbone's fold in
airspeed: no measured orbit lies between it and the fold, so nothing in the data says how
near the fold is, and its slope may be anything from either form's down to zero. On the
rig's truth with orbits 0.2 m/s above the fold, the forms asked that unstable orbit for 5.2
times the truth's amplitude factor, and fits trained at it put the fold 0.09-0.22 m/s below
the truth's, against 0.03-0.04 without it (docs/experiments.md, thirty-seventh session).

The uncertainty of m is not carried (the mechanistic fit gives none for its eigenvalues).
On the rig's noise-free truth at 18-25.5 m/s the unstable orbits' predicted amplitude factor
lies below the truth's, and the stable ones' at most 17 % above it (m at the Hopf point
stands for the orbit's). On a campaign reaching down to 0.2 m/s above the fold (17-23.6
m/s) the next two unstable orbits above the one nearest the fold are asked 1.2 and 1.6
times the truth's factor (tests/test_ude_margins.py).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .backbone import HopfBackbone, backbone_of
from .criticality import equilibrium_eigenvalues, growth_rate_slope
from ..data.orbit import OrbitDataset


# the airspeed step (m/s) of the growth-rate slope's central difference
SLOPE_STEP = 1e-3


@dataclass(frozen=True)
class PredictedMargin:
    """One labelled orbit's prediction: the amplitude's Floquet exponent times the period
    (``exponent_T``, at one standard error towards zero), the other multipliers' factor and
    the indicator's size they give; None throughout where there is no prediction."""
    exponent_T: float | None
    others: float | None
    margin: float | None


@dataclass(frozen=True)
class BranchSlope:
    """The straight line V = a + b s through one stability's labelled orbits: its slope b
    (``slope``) and the slope's standard error (``std``)."""
    slope: float
    std: float

    @classmethod
    def through(cls, s, V) -> "BranchSlope | None":
        """The line through (s, V) by least squares; None for fewer than three orbits
        (no residual to take the error from)."""
        s, V = np.asarray(s, float), np.asarray(V, float)
        if s.size < 3 or np.ptp(s) == 0:
            return None
        X = np.stack([np.ones_like(s), s], axis=1)
        coef, *_ = np.linalg.lstsq(X, V, rcond=None)
        res = V - X @ coef
        var = float(res @ res) / (s.size - 2)
        return cls(float(coef[1]), float(np.sqrt(var * np.linalg.inv(X.T @ X)[1, 1])))


@dataclass(frozen=True)
class BackboneMargins:
    """Every orbit's margin (``values``: nan where the constant one holds), with what they
    were predicted from."""
    values: np.ndarray
    points: tuple[PredictedMargin, ...]
    growth_rate_slope: float
    floor: float
    branch_slopes: dict        # {stable: BranchSlope or None}, in the backbone's s
    next_to_fold: dict         # {stable: that branch's airspeed nearest the fold, or None}

    def to_json(self) -> dict:
        return {"source": "Hopf normal-form backbone and each branch's straight line, the "
                          "slope nearer zero, one standard error towards neutral",
                "growth_rate_slope": self.growth_rate_slope, "floor": self.floor,
                "branch_slopes": {("stable" if k else "unstable"):
                                  None if b is None else {"slope": b.slope, "std": b.std}
                                  for k, b in self.branch_slopes.items()},
                "next_to_fold": {("stable" if k else "unstable"): v
                                 for k, v in self.next_to_fold.items()},
                # margin: the prediction; used: what the training asked (null: the floor)
                "points": [{"exponent_T": p.exponent_T, "others": p.others,
                            "margin": p.margin, "used": None if np.isnan(v) else float(v)}
                           for p, v in zip(self.points, self.values)]}


def _supported(slope: float, std: float, m: float, stable: bool) -> float | None:
    """|slope| moved one standard error towards zero, or None where the label's side is not
    supported (stable where m V'(s) > 0: the exponent's sign, which the label must share)."""
    if not np.isfinite(std) or (m * slope > 0) != stable or abs(slope) <= std:
        return None
    return abs(slope) - std


def predict_margin(backbone: HopfBackbone, m: float, amplitude: float, period: float,
                   stable: bool, other_eigenvalues,
                   branch: BranchSlope | None = None) -> PredictedMargin:
    """The indicator's size the data predicts for one orbit: the backbone's slope, or the
    orbit's branch line's (``branch``) where that is nearer zero (the module docstring)."""
    none = PredictedMargin(None, None, None)
    s = (amplitude / backbone.r_scale) ** 2
    slope = backbone.c1 + 2 * backbone.c2 * s
    grad = np.array([0.0, 1.0, 2 * s])
    sizes = [_supported(slope, float(np.sqrt(max(grad @ backbone.cov @ grad, 0.0))),
                        m, stable)]
    if branch is not None:
        sizes.append(_supported(branch.slope, branch.std, m, stable))
    if None in sizes:
        return none
    exponent_T = -2 * s * m * np.sign(slope) * min(sizes) * period
    others = float(np.prod(np.real(1 - np.exp(np.asarray(other_eigenvalues) * period))))
    size = abs((1 - np.exp(exponent_T)) * others)
    return PredictedMargin(float(exponent_T), others, float(size))


def backbone_margins(ds: OrbitDataset, mech_model, floor: float) -> BackboneMargins | None:
    """Each orbit's margin for the periodic training, never below ``floor``; None where the
    data has no backbone or the mechanistic model's equilibrium does not lose stability the
    way the backbone says (no growth-rate slope of the backbone's sign)."""
    backbone = backbone_of(ds)
    if backbone is None:
        return None
    m = growth_rate_slope(mech_model, backbone.hopf, SLOPE_STEP)
    if not np.isfinite(m) or m * backbone.m_sign <= 0:
        return None
    lines, ends = {}, {}
    for label in (True, False):
        branch = [o for o in ds if o.stable is label and o.amplitude > 0]
        lines[label] = BranchSlope.through([(o.amplitude / backbone.r_scale) ** 2
                                            for o in branch], [o.parameter for o in branch])
        ends[label] = _next_to_fold(backbone, [o.parameter for o in branch])
    points = []
    for o in ds:
        if (o.stable is None or not o.amplitude > 0
                or o.parameter == ends[o.stable]):
            points.append(PredictedMargin(None, None, None))
            continue
        lam = equilibrium_eigenvalues(mech_model, o.parameter)
        others = lam[np.argsort(np.real(lam))[:-2]]
        points.append(predict_margin(backbone, m, o.amplitude, 1.0 / o.frequency,
                                     o.stable, others, lines[o.stable]))
    values = np.array([np.nan if p.margin is None else max(p.margin, floor) for p in points])
    return BackboneMargins(values, tuple(points), float(m), float(floor), lines, ends)


def _next_to_fold(backbone: HopfBackbone, airspeeds: list) -> float | None:
    """The airspeed of a branch's orbits nearest the backbone's fold (the lowest where the
    fold lies below the Hopf point, else the highest); None without a fold or orbits."""
    if backbone.fold is None or not airspeeds:
        return None
    return float(min(airspeeds) if backbone.fold < backbone.hopf else max(airspeeds))
