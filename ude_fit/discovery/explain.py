"""Explaining a mechanistic model's residual as a sparse sum of physically named terms.

On the Fourier-averaged orbits the mechanistic model is linear in its parameters
(equation error, see ``_identify.regression``): per equation, ``b = A theta`` on every
sample. Its residual is what the least-squares fit of ``A`` leaves. Each candidate
*effect* of ``_library`` adds columns; selection, per equation:

* forward stepwise least squares over effects, the mechanistic columns always in (so an
  effect's coefficient is estimated jointly with the parameters it competes with, e.g.
  a cubic spring with the linear one), scored by cross-validation that leaves whole
  orbits out (samples of one orbit are not independent), stopping by the one-standard-
  error rule: the smallest model whose CV error is within one standard error of the
  best one's. No hand-set threshold per case.
* an effect with a shape parameter (a freeplay half-width, a lag's time constant)
  enters with the value the CV error prefers on a grid.
* coefficient uncertainty by a bootstrap over orbits; each selected effect's share of
  the mechanistic residual (what adding it removed, in the order selected) and of the
  equation's whole generalised force (what ranks effects across equations).
* "no significant missing effect" when no effect lowers the CV error by more than the
  baseline's standard error.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..models.library import AERO, Effect, FREQ, LIBRARY, LINEAR, columns, effect, states_of
from ..training.identify import TrainingData, regression


LINEAR_KINDS = (AERO, LINEAR, FREQ)


@dataclass
class Selection:
    equation: int
    effects: list = field(default_factory=list)   # dicts: key, name, terms, shape, coef...
    cv_path: list = field(default_factory=list)   # (effect added, cv mse, se, shape)
    baseline_cv: float = 0.0
    significant: bool = False
    residual_rms: float = 0.0                     # of the mechanistic fit
    force_rms: float = 0.0                        # of the equation's whole force


def _samples(data: TrainingData, system: str):
    """The formulas' sample mapping and each sample's orbit index (orbit-major order)."""
    n_o, n = data.ys.shape[:2]
    return states_of(data, system), np.repeat(np.arange(n_o), n)


def _fold_ids(groups: np.ndarray, k: int, rng) -> np.ndarray:
    ug = np.unique(groups)
    perm = rng.permutation(ug)
    fold_of = {g: i % k for i, g in enumerate(perm)}
    return np.array([fold_of[g] for g in groups])


def _lstsq(X, y):
    return np.linalg.lstsq(X, y, rcond=None)[0]


def _cv(X: np.ndarray, y: np.ndarray, folds: np.ndarray) -> tuple[float, float]:
    """Mean and standard error over folds of the held-out mean squared error."""
    errs = []
    for f in np.unique(folds):
        tr, te = folds != f, folds == f
        r = y[te] - X[te] @ _lstsq(X[tr], y[tr]) if X.shape[1] else y[te]
        errs.append(float(np.mean(r ** 2)))
    errs = np.asarray(errs)
    return float(errs.mean()), float(errs.std(ddof=1) / np.sqrt(len(errs)))


def _normalised(X):
    s = np.sqrt(np.mean(X ** 2, axis=0))
    return X / np.where(s > 0, s, 1.0), np.where(s > 0, s, 1.0)


def _signs_ok(X, y, n_base, keys, cols, by_key) -> bool:
    """Every sign-constrained effect of the joint fit has its physical sign."""
    c = _lstsq(X, y)[n_base:]
    off = 0
    for key in keys:
        w = cols[key][0].shape[1]
        sign = by_key[key[0]].sign
        if sign and np.any(sign * c[off:off + w] < 0):
            return False
        off += w
    return True


def _refine_shape(best, e: Effect, S, cols, B, chosen, yn, fid):
    """The grid's best shape parameter polished by a bounded 1-D search of the CV error
    between its grid neighbours (the grid only brackets it)."""
    (key, d), m, se = best
    if not e.grid:
        return best
    grid = sorted(e.grid(S))
    i = grid.index(d)
    lo, hi = grid[max(i - 1, 0)], grid[min(i + 1, len(grid) - 1)]
    if hi <= lo:
        return best
    from scipy.optimize import minimize_scalar

    def score(x):
        X = np.concatenate([B] + [cols[c][0] for c in chosen]
                           + [_normalised(columns(e, S, float(x)))[0]], 1)
        return _cv(X, yn, fid)[0]
    r = minimize_scalar(score, bounds=(lo, hi), method="bounded",
                        options={"xatol": 1e-3 * d})
    if r.fun >= m:
        return best
    x = float(r.x)
    cols[(key, x)] = _normalised(columns(e, S, x))
    X = np.concatenate([B] + [cols[c][0] for c in chosen] + [cols[(key, x)][0]], 1)
    return ((key, x), *_cv(X, yn, fid))


def select(effects: list[Effect], S: dict, y: np.ndarray, groups: np.ndarray, *,
           equation: int, base: np.ndarray | None = None, folds: int = 5, seed: int = 0,
           max_effects: int = 4, bootstrap: int = 200) -> Selection:
    """Forward stepwise selection of effects for one equation: ``y`` the equation's
    right-hand side, ``base`` the mechanistic model's columns (always in; None: the
    residual itself is regressed)."""
    rng = np.random.default_rng(seed)
    fid = _fold_ids(groups, min(folds, len(np.unique(groups))), rng)
    scale = float(np.sqrt(np.mean(y ** 2))) or 1.0
    yn = y / scale
    B = np.zeros((len(y), 0)) if base is None else _normalised(
        base[:, np.any(base != 0, axis=0)])[0]
    pool = [e for e in effects if e.equation == equation]
    by_key = {e.key: e for e in pool}
    cols = {}
    for e in pool:
        for d in (e.grid(S) if e.grid else (None,)):
            cols[(e.key, d)] = _normalised(columns(e, S, d))
    chosen: list = []
    base_cv, base_se = _cv(B, yn, fid)
    path = [(None, base_cv, base_se)]
    while len(chosen) < max_effects:
        best = None
        for e in pool:
            if any(c[0] == e.key for c in chosen):
                continue
            for (k, d) in [c for c in cols if c[0] == e.key]:
                X = np.concatenate([B] + [cols[c][0] for c in chosen] + [cols[(k, d)][0]], 1)
                if not _signs_ok(X, yn, B.shape[1], chosen + [(k, d)], cols, by_key):
                    continue            # a physically wrong sign: not this combination
                m, se = _cv(X, yn, fid)
                if best is None or m < best[1]:
                    best = ((k, d), m, se)
        if best is None:
            break
        best = _refine_shape(best, by_key[best[0][0]], S, cols, B, chosen, yn, fid)
        chosen.append(best[0])
        path.append(best)
    # one-standard-error rule over the path
    i_best = int(np.argmin([p[1] for p in path]))
    thresh = path[i_best][1] + path[i_best][2]
    k = next(i for i, p in enumerate(path) if p[1] <= thresh)
    chosen = chosen[:k]
    c0 = _lstsq(B, yn) if B.shape[1] else np.zeros(0)
    ssr_base = float(np.sum((yn - B @ c0) ** 2))
    sel = Selection(equation=equation,
                    cv_path=[(p[0][0] if p[0] else None, p[1] * scale ** 2,
                              p[2] * scale ** 2, p[0][1] if p[0] else None) for p in path],
                    baseline_cv=base_cv * scale ** 2,
                    significant=bool(k > 0 and base_cv - path[k][1] > base_se),
                    residual_rms=float(np.sqrt(ssr_base / len(y))) * scale, force_rms=scale)
    if not chosen:
        return sel
    blocks = [cols[c] for c in chosen]
    X = np.concatenate([B] + [b[0] for b in blocks], 1)
    widths = [b[0].shape[1] for b in blocks]
    c_all = _lstsq(X, yn)
    ug = np.unique(groups)
    members = {g: np.flatnonzero(groups == g) for g in ug}
    boots = []
    for _ in range(bootstrap):
        idx = np.concatenate([members[g] for g in rng.choice(ug, size=ug.size, replace=True)])
        boots.append(_lstsq(X[idx], yn[idx]))
    boots = np.asarray(boots)
    ssr_prev, off = ssr_base, B.shape[1]
    for step, ((key, d), (_, s), w) in enumerate(zip(chosen, blocks, widths), start=1):
        sl = slice(off, off + w)
        off += w
        # sequential share: what adding this effect, in the order selected, removed from
        # the residual (drop-one shares vanish when two selected effects are collinear)
        Xk = X[:, :off]
        ssr = float(np.sum((yn - Xk @ _lstsq(Xk, yn)) ** 2))
        coef = c_all[sl] * scale / s
        unc = boots[:, sl].std(axis=0) * scale / s
        e = by_key[key]
        sel.effects.append({
            "key": key, "name": e.name, "kind": e.kind, "equation": equation,
            "terms": list(e.terms), "shape": d, "shape_name": e.shape_name,
            "coefficients": coef.tolist(), "uncertainty": unc.tolist(),
            "share": (ssr_prev - ssr) / ssr_base if ssr_base > 0 else 0.0,
            "force_share": (ssr_prev - ssr) / float(np.sum(yn ** 2)),
            # its own step lowered the CV error by more than the standard error of the
            # model before it (coefficients of collinear effects can each be unsure while
            # the effect as a whole is not)
            "cv_gain": (path[step - 1][1] - path[step][1]) * scale ** 2,
            "significant": bool(path[step - 1][1] - path[step][1] > path[step - 1][2]),
            # at least one coefficient clear of zero by two bootstrap standard errors
            "clear_of_zero": bool(np.any(np.abs(coef) > 2 * unc)),
        })
        ssr_prev = ssr
    sel.effects.sort(key=lambda e: -e["share"])
    return sel


@dataclass
class Explanation:
    system: str
    selections: list              # one Selection per equation
    ranked: list                  # every selected effect, largest force share first
    residual: dict                # per equation: samples of the states and the residual
    significant: bool             # any effect significant at all
    summary: str

    def top(self) -> dict | None:
        return self.ranked[0] if self.ranked else None

    def best_linear_term(self) -> dict | None:
        """The linear, parameter-dependent candidate the forward paths took first (even
        if not significant), from the equation the mechanistic model fits worst: what the
        loop may still try on the diagram (a retuning, never a claim of missing physics)."""
        best = None
        for sel in self.selections:
            for i, (key, _, _, shape) in enumerate(sel.cv_path[1:], start=1):
                e = effect(self.system, key)
                if e.kind in LINEAR_KINDS:
                    rank = (i, -sel.residual_rms / sel.force_rms)
                    if best is None or rank < best[0]:
                        best = (rank, {"key": key, "name": e.name, "kind": e.kind,
                                       "shape": shape, "equation": sel.equation})
                    break
        return None if best is None else best[1]

    def to_dict(self) -> dict:
        return {"system": self.system, "significant": self.significant,
                "summary": self.summary, "ranked": self.ranked,
                "equations": [{"equation": s.equation, "significant": s.significant,
                               "residual_rms": s.residual_rms, "force_rms": s.force_rms,
                               "cv_path": [{"added": a, "cv_mse": m, "se": se, "shape": d}
                                           for a, m, se, d in s.cv_path],
                               "effects": s.effects} for s in self.selections]}


EQUATIONS = {"flutter": ("heave force (N)", "pitch moment (N m)"),
             "oscillator": ("force per unit mass (m/s^2)",)}


def explain(data: TrainingData, system: str, *, added: tuple = (), seed: int = 0,
            folds: int = 5, bootstrap: int = 200, max_effects: int = 4,
            library=None, target: np.ndarray | None = None) -> Explanation:
    """Explain what the least-squares mechanistic model leaves, equation by equation.
    ``added``: (key, shape) effects already in the model (a refined model's residual is
    explained; those effects are no longer candidates). ``target``: (N, n_eq) forces to
    explain instead of the residual, e.g. a learnt UDE correction U on the samples (the
    mechanistic columns stay in, so what U does by retuning them is not credited to an
    effect)."""
    A, b, _, _ = regression(data, system, effects=tuple(added))
    if target is not None:
        b = -np.asarray(target, float).reshape(b.shape)
    S, groups = _samples(data, system)
    done = {k for k, _ in added}
    lib = [e for e in (LIBRARY[system] if library is None else library) if e.key not in done]
    sels, residual = [], {}
    for eq in range(b.shape[1]):
        # y = the generalised force the model must still supply on the right-hand side
        # (regression's b is its negative), so a coefficient is the force per unit column
        y = -b[:, eq]
        sel = select(lib, S, y, groups, equation=eq, base=A[:, eq, :], folds=folds,
                     seed=seed + eq, max_effects=max_effects, bootstrap=bootstrap)
        sels.append(sel)
        Ae = A[:, eq, np.any(A[:, eq, :] != 0, axis=0)]
        residual[eq] = y - Ae @ _lstsq(Ae, y)
    # missing physics first (structural nonlinearities, hidden states), then the linear
    # and parameter-dependent mismatch (retuned parameters, unsteady aerodynamics): the
    # latter is what the quasi-steady aerofoil is known to lack, reported as such
    ranked = sorted((e for s in sels for e in s.effects if e["significant"]),
                    key=lambda e: (e["kind"] in LINEAR_KINDS, -e["force_share"]))
    significant = any(s.significant for s in sels) and bool(ranked)
    return Explanation(system, sels, ranked, {"states": S, "residual": residual,
                                              "groups": groups},
                       significant, _summary(ranked, significant))


def _summary(ranked: list, significant: bool) -> str:
    if not significant:
        return "no significant missing effect: no candidate beats the noise"
    top = ranked[0]
    if all(e["kind"] in LINEAR_KINDS for e in ranked):
        return ("no significant nonlinear effect; the residual is linear and "
                f"parameter-dependent ({top['kind']}: {top['name']})")
    return f"top-ranked missing effect: {top['name']} ({top['kind']})"


def choose_shape(data: TrainingData, system: str, key: str, *, added: tuple = (),
                 seed: int = 0, folds: int = 5):
    """The shape parameter of effect ``key`` (None if it has none) that the leave-orbits-
    out CV error prefers, with the mechanistic columns and ``added`` effects in."""
    e = effect(system, key)
    if not e.grid:
        return None
    A, b, _, _ = regression(data, system, effects=tuple(added))
    S, groups = _samples(data, system)
    fid = _fold_ids(groups, min(folds, int(groups[-1]) + 1), np.random.default_rng(seed))
    Ae = A[:, e.equation, :]
    B = _normalised(Ae[:, np.any(Ae != 0, axis=0)])[0]
    y = -b[:, e.equation]
    y = y / (np.sqrt(np.mean(y ** 2)) or 1.0)
    cols = {(e.key, d): _normalised(columns(e, S, d)) for d in e.grid(S)}
    scores = {c: _cv(np.concatenate([B, cols[c][0]], 1), y, fid) for c in cols}
    c = min(scores, key=lambda c: scores[c][0])
    (_, d), _, _ = _refine_shape((c, *scores[c]), e, S, cols, B, [], y, fid)
    return d
