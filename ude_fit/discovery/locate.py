"""Where is the residual? Additive shape functions of single states, per equation.

The catalogue (``explain``) can only name what it lists. This module asks the question
before naming anything: per equation, the generalised force the mechanistic model leaves
(equation error on the Fourier-averaged orbits, whose q, q', q'' are analytic) is fitted as

    y = [mechanistic columns, linear nuisance columns] theta + sum_s f_s(s) + e,

one smooth shape ``f_s`` per state (and the bifurcation parameter), each a cubic B-spline
with its linear part projected out (a straight line in a state is a retuned linear
parameter, which the mechanistic and nuisance columns already carry) and a second-
difference penalty (Eilers and Marx's P-splines). The nuisance columns are the catalogue's
formula-based *linear* and parameter-dependent linear terms of the equation: a mismatch
that is linear in the states (the quasi-steady aerofoil's missing unsteady aerodynamics)
is not a shape of one state and must not be drawn as one.

* each shape's smoothness is chosen by cross-validation that leaves whole orbits out
  (samples of one orbit are not independent), coordinate-wise over a fixed grid;
* uncertainty bands from the penalised least-squares covariance (the Bayesian one of
  Wahba and Silverman), the noise variance from the residual with the samples of an orbit
  counted as the 2K+1 numbers they are;
* a shape is significant when an approximate F test (Wood's, with an orbit's samples
  counted as the 2K+1 numbers they are) rejects it being zero at 1 %, shared by the
  equation's shapes (Bonferroni), *and* dropping it raises the leave-orbits-out error by
  more than one standard error of the paired per-fold differences (the one-standard-error
  rule ``explain`` uses): conventional levels, nothing fitted to any case;
* ``region``: where the band of the shape, less its best straight line over the data,
  excludes zero (the interval hull; None for an end at the edge of the data).

What a significant shape *is* (a stop, a dead zone, saturation, ...) is ``describe``'s
question (``shapes.py``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.interpolate import BSpline

from .._fourier import K
from ..models.forms import EQUATIONS, STATES, located_states, state_parts
from ..models.library import LIBRARY, STRUCTURAL, HIDDEN, columns, states_of
from ..training.identify import TrainingData, regression
from .explain import _fold_ids

STATE_NAMES = {system: {k: v[0] for k, v in states.items()}
               for system, states in STATES.items()}
EQUATION_NAMES = EQUATIONS

N_INTERVALS = 10                 # knot intervals per state: the penalty sets the smoothness
LAMBDAS = 10.0 ** np.arange(-4, 5)   # relative to the basis's own scale
Z_SIGNIFICANT = 2.0              # conventional two-standard-error band (the region)
LEVEL = 0.01                     # significance level, shared by an equation's shapes


@dataclass
class Shape:
    """One state's shape function in one equation."""
    equation: int
    state: str                    # key of the sample mapping (h, al, ...)
    name: str                     # as reported (h, alpha, h_dot, ...)
    grid: np.ndarray              # where the shape is drawn
    value: np.ndarray             # f_s on the grid (linear part removed)
    band: np.ndarray              # one standard error on the grid
    samples: np.ndarray           # the state on the samples (for the region, the picture)
    partial: np.ndarray           # partial residual on the samples: f_s + e
    lam: float
    edf: float                    # effective degrees of freedom of the shape
    cv_gain: float                # held-out error without the shape minus with it
    cv_gain_se: float
    p_value: float                # F-type test of the shape, orbits counted as 2K+1 numbers
    significant: bool
    share: float                  # of the equation's residual variance this shape explains
    region: dict = field(default_factory=dict)   # {name: [lo | None, hi | None]}
    description: object = None    # a shapes.Description once described

    def to_dict(self) -> dict:
        d = {"equation": self.equation, "state": self.name, "lambda": self.lam,
             "edf": self.edf, "cv_gain": self.cv_gain, "cv_gain_se": self.cv_gain_se, "p_value": self.p_value,
             "significant": self.significant, "share": self.share, "region": self.region}
        if self.description is not None:
            d["description"] = self.description.to_dict()
        return d


@dataclass
class EquationLocation:
    equation: int
    name: str
    shapes: list                  # Shape per state, largest cv_gain first
    residual_rms: float           # of the mechanistic (+ nuisance) fit
    noise_rms: float              # of the full additive fit
    design: object = None         # what shapes.describe refits with (internal)

    @property
    def significant(self) -> list:
        return [s for s in self.shapes if s.significant]


@dataclass
class Location:
    system: str
    equations: list

    def significant(self) -> list:
        """Every significant shape, largest held-out gain relative to its equation's
        residual first."""
        out = [s for e in self.equations for s in e.significant]
        rms = {e.equation: e.residual_rms or 1.0 for e in self.equations}
        return sorted(out, key=lambda s: -s.cv_gain / rms[s.equation] ** 2)

    def summary(self) -> str:
        sig = self.significant()
        if not sig:
            return "no shape of a single state beats the noise"
        s = sig[0]
        eq = EQUATION_NAMES[self.system][s.equation]
        what = s.description.phrase() if s.description is not None else "a shape"
        return f"an effect in {eq} depending on {s.name}: {what}"

    def to_dict(self) -> dict:
        return {"system": self.system, "summary": self.summary(),
                "equations": [{"equation": e.name, "residual_rms": e.residual_rms,
                               "noise_rms": e.noise_rms,
                               "shapes": [s.to_dict() for s in e.shapes]}
                              for e in self.equations]}


# ---------------------------------------------------------------------------------------
# penalised regression splines
# ---------------------------------------------------------------------------------------

def spline_basis(x: np.ndarray, lo: float, hi: float, n_intervals: int = N_INTERVALS):
    """Cubic B-spline design matrix on [lo, hi] (equal knots) and its second-difference
    penalty's square root."""
    k = 3
    inner = np.linspace(lo, hi, n_intervals + 1)
    t = np.concatenate([[lo] * k, inner, [hi] * k])
    B = BSpline.design_matrix(np.clip(x, lo, hi), t, k).toarray()
    D = np.diff(np.eye(B.shape[1]), n=2, axis=0)
    return B, D


def _detrend(B: np.ndarray, L: np.ndarray) -> np.ndarray:
    """B with its projection on the columns L (constant, the state) removed."""
    return B - L @ np.linalg.lstsq(L, B, rcond=None)[0]


@dataclass
class _Smooth:
    key: str
    lo: float
    hi: float
    trend: np.ndarray             # B's projection coefficients on [1, x] (or on [1])
    X: np.ndarray                 # detrended basis on the samples (times v), scaled
    D: np.ndarray                 # penalty root (scaled alike)
    scale: float

    def basis(self, x: np.ndarray) -> np.ndarray:
        """The shape's basis on ``x`` (a coefficient function for a shape times v)."""
        B, _ = spline_basis(x, self.lo, self.hi)
        L = np.stack([np.ones_like(x), x], 1)[:, :len(self.trend)]
        return (B - L @ self.trend) / self.scale


def _smooth(key: str, x: np.ndarray, times: np.ndarray | None = None) -> _Smooth | None:
    """A shape of x, or with ``times`` a coefficient f(x) multiplying ``times`` (a damping
    depending on x): then only its constant is projected out (a constant times v is the
    linear damping the mechanistic model has), its slope is a bilinear x v, a shape."""
    lo, hi = float(np.min(x)), float(np.max(x))
    if not hi > lo:
        return None
    B, D = spline_basis(x, lo, hi)
    if times is None:
        L = np.stack([np.ones_like(x), x], 1)
        trend = np.linalg.lstsq(L, B, rcond=None)[0]
        X = B - L @ trend
    else:
        v = np.asarray(times, float)[:, None]
        trend = np.linalg.lstsq(v, B * v, rcond=None)[0]
        X = (B - trend) * v
    scale = float(np.sqrt(np.mean(X ** 2))) or 1.0
    return _Smooth(key, lo, hi, trend, X / scale, D, scale)


def _smooth_of(key: str, S: dict) -> _Smooth | None:
    state, times = state_parts(key)
    return _smooth(key, np.asarray(S[state], float),
                   None if times is None else np.asarray(S[times], float))


def _solve_normal(G, g):
    """(G) b = g for a penalised Gram matrix G; a relative ridge of 1e-10 keeps the null
    directions (a basis's straight line, projected out) at zero."""
    d = np.diag(G)
    ridge = 1e-10 * (float(d.mean()) or 1.0)
    return np.linalg.solve(G + ridge * np.eye(len(G)), g)


class _Design:
    """Unpenalised columns N and penalised smooths, with one lambda per smooth. Held-out
    errors by Gram matrices: each fold's training Gram is the whole one less the fold's."""

    def __init__(self, N: np.ndarray, smooths: list, y: np.ndarray, folds: np.ndarray):
        self.N, self.smooths = N, smooths
        self.lams = [1.0] * len(smooths)
        self.X = np.concatenate([N] + [s.X for s in smooths], 1)
        self.y, self.folds = y, folds
        self.slices, off = [], N.shape[1]
        for s in smooths:
            self.slices.append(slice(off, off + s.X.shape[1]))
            off += s.X.shape[1]
        self.penalties = [s.D.T @ s.D for s in smooths]
        self.XtX, self.Xty = self.X.T @ self.X, self.X.T @ y
        self.parts = []
        for f in np.unique(folds):
            te = folds == f
            Xt = self.X[te]
            self.parts.append((te, Xt.T @ Xt, Xt.T @ y[te]))

    def _keep(self, skip):
        idx = np.arange(self.X.shape[1])
        if skip is None:
            return idx
        return np.setdiff1d(idx, np.arange(self.X.shape[1])[self.slices[skip]])

    def penalty(self, lams=None) -> np.ndarray:
        lams = self.lams if lams is None else lams
        P = np.zeros_like(self.XtX)
        for sl, Pi, lam in zip(self.slices, self.penalties, lams):
            P[sl, sl] = lam * Pi
        return P

    def fit(self, skip=None, lams=None):
        keep = self._keep(skip)
        G = (self.XtX + self.penalty(lams))[np.ix_(keep, keep)]
        return keep, _solve_normal(G, self.Xty[keep])

    def fold_errors(self, y=None, folds=None, skip=None, lams=None) -> np.ndarray:
        keep = self._keep(skip)
        G0 = (self.XtX + self.penalty(lams))[np.ix_(keep, keep)]
        out = []
        for te, Gf, gf in self.parts:
            b = _solve_normal(G0 - Gf[np.ix_(keep, keep)], self.Xty[keep] - gf[keep])
            out.append(float(np.mean((self.y[te] - self.X[te][:, keep] @ b) ** 2)))
        return np.asarray(out)

    def choose_lambdas(self, y, folds, sweeps: int = 2):
        for _ in range(sweeps):
            for i in range(len(self.smooths)):
                best = None
                for lam in LAMBDAS:
                    trial = list(self.lams)
                    trial[i] = float(lam)
                    m = float(self.fold_errors(lams=trial).mean())
                    if best is None or m < best[0]:
                        best = (m, float(lam))
                self.lams[i] = best[1]


def _effective_n(n: int, per_orbit: int) -> float:
    """Independent numbers in n samples of K-harmonic orbits sampled ``per_orbit`` times."""
    return n * min(1.0, (2 * K + 1) / per_orbit)


def locate_equation(S: dict, y: np.ndarray, groups: np.ndarray, *, equation: int,
                    base: np.ndarray, states: dict, nuisance: np.ndarray | None = None,
                    folds: int = 10, seed: int = 0, per_orbit: int | None = None
                    ) -> EquationLocation:
    """Shape functions of the states ``states`` ({key: name}) for one equation: ``y`` its
    right-hand side still to be supplied, ``base`` the mechanistic columns (N, p)."""
    n = len(y)
    per_orbit = per_orbit or int(S.get("n", n))
    scale = float(np.sqrt(np.mean(y ** 2))) or 1.0
    yn = y / scale
    lin = [np.ones(n)] + [np.asarray(S[k], float) for k in states if "*" not in k]
    cols = [base[:, np.any(base != 0, axis=0)]] + [np.stack(lin, 1)]
    if nuisance is not None and nuisance.size:
        cols.append(nuisance)
    N = np.concatenate(cols, 1)
    N = N / np.where(np.sqrt(np.mean(N ** 2, 0)) > 0, np.sqrt(np.mean(N ** 2, 0)), 1.0)
    smooths = [s for s in (_smooth_of(k, S) for k in states) if s]
    fid = _fold_ids(groups, min(folds, len(np.unique(groups))), np.random.default_rng(seed))
    design = _Design(N, smooths, yn, fid)
    design.choose_lambdas(yn, fid)
    full = design.fold_errors()
    X = design.X
    _, b = design.fit()
    res = yn - X @ b
    # covariance of the penalised estimate: sigma^2 (X'X + P'P)^-1 X'X (X'X + P'P)^-1
    # is the frequentist one; the Bayesian sigma^2 (X'X + P'P)^-1 has the better coverage
    G = np.linalg.pinv(design.XtX + design.penalty())
    edf_all = float(np.trace(G @ design.XtX))
    n_eff = _effective_n(n, per_orbit)
    sigma2 = float(res @ res) / max(n - edf_all, 1.0) * (n / n_eff)
    r0 = yn - N @ np.linalg.lstsq(N, yn, rcond=None)[0]
    ss0 = float(r0 @ r0)
    shapes, off = [], N.shape[1]
    F = G @ design.XtX
    for i, sm in enumerate(smooths):
        w = sm.X.shape[1]
        sl = slice(off, off + w)
        off += w
        drop = design.fold_errors(skip=i)
        diff = drop - full
        gain = float(diff.mean())
        se = float(diff.std(ddof=1) / np.sqrt(len(diff))) if len(diff) > 1 else np.inf
        keep, b0 = design.fit(skip=i)
        r0 = yn - X[:, keep] @ b0
        edf = float(np.trace(F[sl, sl]))
        p = _f_test(float(r0 @ r0), float(res @ res), edf, n, n_eff, edf_all)
        grid = np.linspace(sm.lo, sm.hi, 101)
        Bg = sm.basis(grid)
        value = Bg @ b[sl]
        band = np.sqrt(np.maximum(np.einsum("ij,jk,ik->i", Bg, G[sl, sl], Bg), 0) * sigma2)
        x = np.asarray(S[state_parts(sm.key)[0]], float)
        fs = sm.X @ b[sl]
        share = float(np.sum(fs ** 2)) / ss0 if ss0 > 0 else 0.0
        shape = Shape(equation, sm.key, states[sm.key], grid, value * scale, band * scale,
                      x, _partial(sm.key, S, (fs + res) * scale), design.lams[i], edf,
                      gain * scale ** 2, se * scale ** 2, p,
                      bool(gain > se and p < LEVEL / len(smooths)), share)
        shape.region = {shape.name: _region(grid, value, band)}
        shapes.append(shape)
    shapes.sort(key=lambda s: -s.cv_gain)
    loc = EquationLocation(equation, "", shapes, float(np.sqrt(ss0 / n)) * scale,
                           float(np.sqrt(np.mean(res ** 2))) * scale)
    loc.design = (design, yn, scale, fid, n_eff)
    return loc


def _partial(key: str, S: dict, r: np.ndarray) -> np.ndarray:
    """The partial residual as the shape reads it: for a coefficient of a velocity, the
    force over the velocity where the velocity is at least its median size (nan elsewhere,
    where the quotient is noise)."""
    times = state_parts(key)[1]
    if times is None:
        return r
    v = np.asarray(S[times], float)
    big = np.abs(v) >= np.median(np.abs(v))
    return np.where(big, r / np.where(big, v, 1.0), np.nan)


def _f_test(rss0: float, rss1: float, edf: float, n: int, n_eff: float,
             edf_all: float) -> float:
    """p-value of an approximate F test of a penalised shape (Wood, GAMs, sec. 6.12):
    the residual sums scaled to the independent numbers the samples carry."""
    from scipy.stats import f as f_dist
    d2 = n_eff - edf_all
    if edf <= 0 or d2 <= 1 or rss1 <= 0:
        return 1.0
    stat = (max(rss0 - rss1, 0.0) / edf) / (rss1 / d2)
    return float(f_dist.sf(stat, edf, d2))


def _region(grid, value, band) -> list | None:
    """The interval where the shape less its best line over the grid is clear of zero by
    two standard errors (None ends: the edge of the data); None if nowhere."""
    L = np.stack([np.ones_like(grid), grid], 1)
    dev = value - L @ np.linalg.lstsq(L, value, rcond=None)[0]
    clear = np.abs(dev) > Z_SIGNIFICANT * band
    if not clear.any():
        return None
    i, j = np.flatnonzero(clear)[[0, -1]]
    return [None if i == 0 else float(grid[i]), None if j == len(grid) - 1 else float(grid[j])]


def nuisance_columns(system: str, S: dict, equation: int) -> np.ndarray:
    """The catalogue's linear and parameter-dependent linear terms of one equation that
    need no shape parameter (retuned couplings, airspeed-dependent terms, the Jones wake
    lag of textbook constants: what a quasi-steady model is known to lack): nuisance for
    the locator, so a linear mismatch is not drawn as a shape of one state."""
    out = [columns(e, S, None) for e in LIBRARY[system]
           if e.equation == equation and e.kind not in (STRUCTURAL, HIDDEN) and not e.grid]
    return np.concatenate(out, 1) if out else np.zeros((len(S["w"]), 0))


def locate(data: TrainingData, system: str, *, added: tuple = (), seed: int = 0,
           folds: int = 10, target: np.ndarray | None = None,
           damping_shapes: bool = False) -> Location:
    """Shape functions of every state per equation of what the (refined) mechanistic model
    leaves; ``target`` (N, n_eq): forces to locate instead (e.g. a UDE's correction).
    ``damping_shapes``: also each displacement as the coefficient of the equation's own
    velocity (position-dependent damping, ``forms.located_states``). Off by default: fitted
    together with the single states, a shape of h' and the coefficient of h' depending on h
    share what they explain (concurvity), and on the aerofoil's direction-dependent heave
    damping neither was significant any more (measured, docs/experiments.md)."""
    A, b, _, _ = regression(data, system, effects=tuple(added))
    if target is not None:
        b = -np.asarray(target, float).reshape(b.shape)
    S = states_of(data, system)
    n_o, n = data.ys.shape[:2]
    groups = np.repeat(np.arange(n_o), n)
    eqs = []
    for eq in range(b.shape[1]):
        loc = locate_equation(S, -b[:, eq], groups, equation=eq, base=A[:, eq, :],
                              states=(located_states(system, eq) if damping_shapes
                                      else STATE_NAMES[system]),
                              nuisance=nuisance_columns(system, S, eq), folds=folds,
                              seed=seed + eq, per_orbit=n)
        loc.name = EQUATION_NAMES[system][eq]
        eqs.append(loc)
    return Location(system, eqs)
