"""Explaining a mechanistic model's residual as a sparse sum of physically named terms.

The residual is what the mechanistic model leaves on every sample of the averaged orbits
(:func:`ude_fit.residual_forces`): a generalised force per equation. Each candidate
*effect* (cubic heave stiffness, Coulomb friction in heave, pitch freeplay, ...) is one or
more columns evaluated on the same samples. Selection, per equation:

* forward stepwise least squares over effects, scored by cross-validation that leaves
  whole orbits out (samples of one orbit are not independent), stopping by the one-
  standard-error rule: the smallest model whose CV error is within one standard error of
  the best one's. No hand-set threshold per case.
* an effect with a shape parameter (the freeplay half-width, the friction's smoothing
  velocity, a lag's time constant) enters with the value the CV error prefers on a grid.
* coefficient uncertainty by a bootstrap over orbits; the share of the residual each
  selected effect explains (drop-one reduction of the explained sum of squares).
* "no significant missing effect" when no effect lowers the CV error by more than its
  standard error.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

HEAVE_FRICTION_VS = 1e-3     # m/s: smoothing of sign(h') (tanh); below the orbits' speeds
PITCH_FRICTION_VS = 1e-2     # rad/s


@dataclass(frozen=True)
class Effect:
    """A named physical effect: columns over the sample states, per equation."""
    name: str
    equation: int                     # 0: heave (or the oscillator's only equation), 1: pitch
    terms: tuple[str, ...]            # human-readable formulas of the columns
    columns: object                   # callable(S: dict, shape) -> (N, len(terms))
    shapes: tuple = (None,)           # grid of the shape parameter (None: none)
    shape_name: str = ""


def _sat(x, d):
    return np.clip(x, -d, d)


def lag(S: dict, x: np.ndarray, tau: float) -> np.ndarray:
    """z with tau z' + z = x along each periodic orbit (its steady periodic solution):
    harmonic k of x divided by 1 + i k omega tau. ``S["n"]`` samples per orbit, uniform in
    phase; ``S["omega"]`` the orbit's angular frequency at each sample. This is how a hidden
    first-order state (an aerodynamic lag, a coil current) shows on a periodic orbit."""
    n = int(S["n"])
    X = np.fft.rfft(np.asarray(x, float).reshape(-1, n), axis=1)
    w = np.asarray(S["omega"]).reshape(-1, n)[:, :1]
    k = np.arange(X.shape[1])[None, :]
    return np.fft.irfft(X / (1 + 1j * k * w * tau), n=n, axis=1).ravel()


def _tau_grid(S: dict) -> tuple:
    period = 2 * np.pi / float(np.median(S["omega"]))
    return tuple(float(x) for x in period * np.array([0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0,
                                                      2.0]))


def flutter_library(S: dict) -> list[Effect]:
    """Candidate effects for the aerofoil. S: arrays over the samples h, al, hd, ad, V,
    omega (the orbit's angular frequency), and n (samples per orbit, orbit-major order)."""
    al_max = float(np.max(np.abs(S["al"]))) or 1.0
    fp_grid = tuple(float(x) for x in al_max * np.array([0.02, 0.05, 0.1, 0.15, 0.2, 0.3,
                                                        0.4, 0.5]))
    L = [
        Effect("cubic heave stiffness", 0, ("h^3",), lambda S, _: S["h"][:, None] ** 3),
        Effect("heave stiffness, 5th and 7th order", 0, ("h^5", "h^7"),
               lambda S, _: np.stack([S["h"] ** 5, S["h"] ** 7], 1)),
        Effect("quadratic heave stiffness", 0, ("h^2",), lambda S, _: S["h"][:, None] ** 2),
        Effect("linear heave damping", 0, ("h'",), lambda S, _: S["hd"][:, None]),
        Effect("cubic heave damping", 0, ("h'^3",), lambda S, _: S["hd"][:, None] ** 3),
        Effect("quadratic heave damping", 0, ("|h'| h'",),
               lambda S, _: (np.abs(S["hd"]) * S["hd"])[:, None]),
        Effect("Coulomb friction in heave", 0, ("tanh(h'/1e-3 m/s)",),
               lambda S, _: np.tanh(S["hd"] / HEAVE_FRICTION_VS)[:, None]),
        Effect("linear heave stiffness", 0, ("h",), lambda S, _: S["h"][:, None]),
        Effect("airspeed-dependent heave terms", 0, ("V h", "V^2 h", "V h'"),
               lambda S, _: np.stack([S["V"] * S["h"], S["V"] ** 2 * S["h"],
                                      S["V"] * S["hd"]], 1)),
        Effect("aerodynamic lag state in heave (first-order lag of V h', V^2 alpha)", 0,
               ("lag_tau(V h')", "lag_tau(V^2 alpha)"),
               lambda S, t: np.stack([lag(S, S["V"] * S["hd"], t),
                                      lag(S, S["V"] ** 2 * S["al"], t)], 1),
               _tau_grid(S), "tau (s)"),
        Effect("pitch coupling in heave", 0, ("alpha", "h alpha"),
               lambda S, _: np.stack([S["al"], S["h"] * S["al"]], 1)),
        Effect("pitch freeplay", 1, ("sat(alpha, delta)",),
               lambda S, d: _sat(S["al"], d)[:, None], fp_grid, "delta (rad)"),
        Effect("pitch stiffness, 5th and 7th order", 1, ("alpha^5", "alpha^7"),
               lambda S, _: np.stack([S["al"] ** 5, S["al"] ** 7], 1)),
        Effect("linear pitch damping", 1, ("alpha'",), lambda S, _: S["ad"][:, None]),
        Effect("cubic pitch damping", 1, ("alpha'^3",), lambda S, _: S["ad"][:, None] ** 3),
        Effect("quadratic pitch damping", 1, ("|alpha'| alpha'",),
               lambda S, _: (np.abs(S["ad"]) * S["ad"])[:, None]),
        Effect("Coulomb friction in pitch", 1, ("tanh(alpha'/1e-2 rad/s)",),
               lambda S, _: np.tanh(S["ad"] / PITCH_FRICTION_VS)[:, None]),
        Effect("linear pitch stiffness", 1, ("alpha",), lambda S, _: S["al"][:, None]),
        Effect("airspeed-dependent pitch terms", 1, ("V alpha", "V^2 alpha", "V alpha'"),
               lambda S, _: np.stack([S["V"] * S["al"], S["V"] ** 2 * S["al"],
                                      S["V"] * S["ad"]], 1)),
        Effect("aerodynamic lag state in pitch (first-order lag of V h', V^2 alpha)", 1,
               ("lag_tau(V h')", "lag_tau(V^2 alpha)"),
               lambda S, t: np.stack([lag(S, S["V"] * S["hd"], t),
                                      lag(S, S["V"] ** 2 * S["al"], t)], 1),
               _tau_grid(S), "tau (s)"),
        Effect("heave coupling in pitch", 1, ("h", "h alpha"),
               lambda S, _: np.stack([S["h"], S["h"] * S["al"]], 1)),
    ]
    return L


@dataclass
class Selection:
    equation: int
    effects: list = field(default_factory=list)   # dicts: name, terms, shape, coefficients...
    cv_path: list = field(default_factory=list)   # (effect added, cv mse, se)
    baseline_cv: float = 0.0
    significant: bool = False


def _fold_ids(groups: np.ndarray, k: int, rng) -> np.ndarray:
    ug = np.unique(groups)
    perm = rng.permutation(ug)
    fold_of = {g: i % k for i, g in enumerate(perm)}
    return np.array([fold_of[g] for g in groups])


def _cv(X: np.ndarray, y: np.ndarray, folds: np.ndarray) -> tuple[float, float]:
    """Mean and standard error over folds of the held-out mean squared error."""
    errs = []
    for f in np.unique(folds):
        tr, te = folds != f, folds == f
        if X.shape[1]:
            c, *_ = np.linalg.lstsq(X[tr], y[tr], rcond=None)
            r = y[te] - X[te] @ c
        else:
            r = y[te]
        errs.append(float(np.mean(r ** 2)))
    errs = np.asarray(errs)
    return float(errs.mean()), float(errs.std(ddof=1) / np.sqrt(len(errs)))


def select(effects: list[Effect], S: dict, y: np.ndarray, groups: np.ndarray, *,
           equation: int, folds: int = 5, seed: int = 0, max_effects: int = 4,
           bootstrap: int = 200) -> Selection:
    """Forward stepwise selection of effects for one equation's residual ``y``."""
    rng = np.random.default_rng(seed)
    fid = _fold_ids(groups, min(folds, len(np.unique(groups))), rng)
    scale = float(np.sqrt(np.mean(y ** 2))) or 1.0
    yn = y / scale
    pool = [e for e in effects if e.equation == equation]
    cols = {}
    for e in pool:
        for d in e.shapes:
            X = np.asarray(e.columns(S, d), float)
            s = np.sqrt(np.mean(X ** 2, axis=0))
            cols[(e.name, d)] = (X / np.where(s > 0, s, 1.0), s)
    chosen: list = []
    base_cv, base_se = _cv(np.zeros((len(y), 0)), yn, fid)
    path = [(None, base_cv, base_se)]
    while len(chosen) < max_effects:
        best = None
        for e in pool:
            if any(c[0] == e.name for c in chosen):
                continue
            for d in e.shapes:
                X = np.concatenate([cols[c][0] for c in chosen] + [cols[(e.name, d)][0]], 1)
                m, se = _cv(X, yn, fid)
                if best is None or m < best[1]:
                    best = ((e.name, d), m, se)
        if best is None:
            break
        chosen.append(best[0])
        path.append(best)
    # one-standard-error rule over the path
    i_best = int(np.argmin([p[1] for p in path]))
    thresh = path[i_best][1] + path[i_best][2]
    k = next(i for i, p in enumerate(path) if p[1] <= thresh)
    chosen = chosen[:k]
    sel = Selection(equation=equation, cv_path=[(p[0][0] if p[0] else None, p[1] * scale ** 2,
                                                 p[2] * scale ** 2) for p in path],
                    baseline_cv=base_cv * scale ** 2,
                    significant=bool(k > 0 and base_cv - path[k][1] > base_se))
    if not chosen:
        return sel
    X = np.concatenate([cols[c][0] for c in chosen], 1)
    widths = [cols[c][0].shape[1] for c in chosen]
    colscale = np.concatenate([cols[c][1] for c in chosen])
    c_all, *_ = np.linalg.lstsq(X, yn, rcond=None)
    # bootstrap over orbits
    ug = np.unique(groups)
    boots = []
    for _ in range(bootstrap):
        pick = rng.choice(ug, size=ug.size, replace=True)
        idx = np.concatenate([np.flatnonzero(groups == g) for g in pick])
        cb, *_ = np.linalg.lstsq(X[idx], yn[idx], rcond=None)
        boots.append(cb)
    boots = np.asarray(boots)
    resid_full = float(np.sum((yn - X @ c_all) ** 2))
    off = 0
    by_name = {e.name: e for e in pool}
    for (name, d), w in zip(chosen, widths):
        sl = slice(off, off + w)
        off += w
        keep = np.ones(X.shape[1], bool)
        keep[sl] = False
        if keep.any():
            c_red, *_ = np.linalg.lstsq(X[:, keep], yn, rcond=None)
            resid_red = float(np.sum((yn - X[:, keep] @ c_red) ** 2))
        else:
            resid_red = float(np.sum(yn ** 2))
        coef = c_all[sl] * scale / colscale[sl]
        unc = boots[:, sl].std(axis=0) * scale / colscale[sl]
        sel.effects.append({
            "name": name, "equation": equation, "terms": list(by_name[name].terms),
            "shape": d, "shape_name": by_name[name].shape_name,
            "coefficients": coef.tolist(), "uncertainty": unc.tolist(),
            "share": (resid_red - resid_full) / float(np.sum(yn ** 2)),
        })
    sel.effects.sort(key=lambda e: -e["share"])
    return sel
