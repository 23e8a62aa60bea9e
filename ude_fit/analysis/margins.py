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
the trivial multiplier and the amplitude's). The margin is that indicator with V'(s) moved
one standard error (the backbone's covariance) towards zero: what the data supports at one
sigma. Where the backbone's stability disagrees with the label, or V'(s) is within one
standard error of zero (next to the fold, where the normal form is least exact), there is
no prediction and the configured constant margin holds; it is also the least margin.

The uncertainty of m is not carried (the mechanistic fit gives none for its eigenvalues).
On the rig's noise-free truth the unstable orbits' predicted amplitude factor lies below the
truth's (tests/test_ude_margins.py): the margin asks less than the physics gives.
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
class BackboneMargins:
    """Every orbit's margin (``values``: nan where the constant one holds), with what they
    were predicted from."""
    values: np.ndarray
    points: tuple[PredictedMargin, ...]
    growth_rate_slope: float
    floor: float

    def to_json(self) -> dict:
        return {"source": "Hopf normal-form backbone, one standard error towards neutral",
                "growth_rate_slope": self.growth_rate_slope, "floor": self.floor,
                # margin: the prediction; used: what the training asked (null: the floor)
                "points": [{"exponent_T": p.exponent_T, "others": p.others,
                            "margin": p.margin, "used": None if np.isnan(v) else float(v)}
                           for p, v in zip(self.points, self.values)]}


def predict_margin(backbone: HopfBackbone, m: float, amplitude: float, period: float,
                   stable: bool, other_eigenvalues) -> PredictedMargin:
    """The indicator's size the backbone predicts for one orbit (see the module docstring)."""
    none = PredictedMargin(None, None, None)
    s = (amplitude / backbone.r_scale) ** 2
    slope = backbone.c1 + 2 * backbone.c2 * s
    grad = np.array([0.0, 1.0, 2 * s])
    std = float(np.sqrt(max(grad @ backbone.cov @ grad, 0.0)))
    # stable where m V'(s) > 0: the exponent's sign, which the label must share
    if not np.isfinite(std) or (m * slope > 0) != stable or abs(slope) <= std:
        return none
    exponent_T = -2 * s * m * np.sign(slope) * (abs(slope) - std) * period
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
    points = []
    for o in ds:
        if o.stable is None or not o.amplitude > 0:
            points.append(PredictedMargin(None, None, None))
            continue
        lam = equilibrium_eigenvalues(mech_model, o.parameter)
        others = lam[np.argsort(np.real(lam))[:-2]]
        points.append(predict_margin(backbone, m, o.amplitude, 1.0 / o.frequency,
                                     o.stable, others))
    values = np.array([np.nan if p.margin is None else max(p.margin, floor) for p in points])
    return BackboneMargins(values, tuple(points), float(m), float(floor))
