"""A one-fold curve through the measured points: the diagram's shape, fitted without a model.

For aerofoil data with stable and unstable orbits, the picture the physics allows is one
Hopf point, an unstable branch shrinking towards it, one fold, and a stable branch growing
from the fold. Here the airspeed of the orbit of heave amplitude s (in units of the largest
measured one) is

    V(s) = V_H + ∫₀ˢ c u (u − s_f) e^(β u) du,      c > 0,

so V' changes sign once, at s_f: exactly one Hopf point (s = 0, where V − V_H ∝ s², as in
the normal form), one fold at s_f, unstable orbits below it and stable ones above. It is the
normal form's shape (β = 0, V a cubic in s) with one more freedom, an exponential tilt, which
lets the stable branch grow nearly linearly in s while the unstable branch stays flat, as
the wind-tunnel points do (:mod:`ude_fit.analysis.backbone`'s form in s² cannot: its points
are 9.9 % off on lee2020/model2, this curve's 5.2 %). More freedom (a tilt that is itself
piecewise linear) fitted the 11 lee2020 points closer but put the fold anywhere from 15 to
20 m/s.

Fitted by orthogonal distance in the diagram's plane (airspeed in units of the measured
span, amplitude in units of the largest orbit): every point's foot on the curve is an
unknown held on the side its stability says. The fit guides the UDE between and beyond the
measured orbits (:mod:`ude_fit.training.guides`).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from .orbit import OrbitDataset

_GRID = 801          # samples of the integral over [0, top]
_RESTARTS = 24       # seeded random starts of the orthogonal-distance fit


@dataclass(frozen=True)
class OneFoldCurve:
    """V(s) = hopf + ∫₀ˢ c u (u − fold_s) e^(tilt u) du, s = amplitude / amp_scale."""
    hopf: float            # m/s
    fold_s: float          # the fold's amplitude over amp_scale
    log_c: float
    tilt: float
    amp_scale: float       # m: the largest measured heave amplitude
    top: float             # the curve is defined on [0, top] in s
    amplitude_rms: float   # the points' amplitude errors at their airspeeds, over amp_scale

    def airspeed(self, s) -> np.ndarray:
        """The airspeed of the curve's orbit at ``s`` (in [0, top])."""
        u = np.linspace(0.0, self.top, _GRID)
        return np.interp(np.asarray(s, float), u, _integral(self.hopf, self.fold_s,
                                                            self.log_c, self.tilt, u))

    def unstable(self, s) -> np.ndarray:
        return np.asarray(s, float) < self.fold_s

    @property
    def fold(self) -> float:
        """The fold's airspeed."""
        return float(self.airspeed(self.fold_s))

    def to_json(self) -> dict:
        return {"form": "V(s) = V_H + integral_0^s c u (u - s_f) exp(tilt u) du",
                "hopf": self.hopf, "fold": self.fold, "fold_amplitude":
                self.fold_s * self.amp_scale, "log_c": self.log_c, "tilt": self.tilt,
                "amplitude_rms": self.amplitude_rms}


def _integral(hopf, fold_s, log_c, tilt, u):
    d = np.exp(log_c) * u * (u - fold_s) * np.exp(np.clip(tilt * u, -50.0, 50.0))
    return hopf + np.concatenate([[0.0], np.cumsum(0.5 * (d[1:] + d[:-1]) * np.diff(u))])


def _sigmoid(z):
    return 1.0 / (1.0 + np.exp(-z))


def fit_one_fold(ds: OrbitDataset, top: float) -> OneFoldCurve | None:
    """The curve through ``ds``'s labelled points, defined up to ``top`` times the largest
    amplitude; None where the data has no stable and unstable points to place a fold
    between."""
    pts = [o for o in ds if o.stable is not None]
    unstable = np.array([o.stable is False for o in pts])
    if not pts or unstable.all() or not unstable.any():
        return None
    V = np.array([o.parameter for o in pts], float)
    amp = np.array([o.amplitude for o in pts], float)
    scale = float(amp.max())
    s_pt = amp / scale
    v_span = float(V.max() - V.min()) or 1.0
    u = np.linspace(0.0, top, _GRID)
    lo, hi = 0.01 * top, 0.99 * top       # where the fold may lie

    def unpack(x):
        return x[0], lo + (hi - lo) * _sigmoid(x[1]), x[2], x[3], x[4:]

    def residuals(x):
        hopf, fold_s, log_c, tilt, z = unpack(x)
        # each foot on its stability's side of the fold
        foot = np.where(unstable, fold_s * _sigmoid(z), fold_s + (top - fold_s) * _sigmoid(z))
        v_foot = np.interp(foot, u, _integral(hopf, fold_s, log_c, tilt, u))
        return np.concatenate([(v_foot - V) / v_span, foot - s_pt])

    rng = np.random.default_rng(0)
    best = None
    for _ in range(_RESTARTS):
        x0 = np.concatenate([[V.max() + rng.uniform(0.0, 0.3) * v_span, rng.normal(),
                              np.log(v_span) + rng.normal(), rng.normal()],
                             rng.normal(size=len(pts))])
        res = least_squares(residuals, x0)
        if best is None or res.cost < best.cost:
            best = res
    hopf, fold_s, log_c, tilt, _ = unpack(best.x)
    curve = OneFoldCurve(float(hopf), float(fold_s), float(log_c), float(tilt), scale,
                         float(top), amplitude_rms=0.0)
    return dataclasses.replace(curve,
                               amplitude_rms=_amplitude_rms(curve, V, s_pt, unstable))


def _amplitude_rms(curve: OneFoldCurve, V, s_pt, unstable) -> float:
    """Each point against the curve's orbit at its airspeed on its stability's side
    (nearest in airspeed where the side does not reach it), as the metrics judge a model."""
    u = np.linspace(0.0, curve.top, _GRID)
    v = curve.airspeed(u)
    errs = []
    for Vi, si, ui in zip(V, s_pt, unstable):
        side = u <= curve.fold_s if ui else u >= curve.fold_s
        j = np.argmin(np.abs(v[side] - Vi))
        errs.append(u[side][j] - si)
    return float(np.sqrt(np.mean(np.square(errs))))
