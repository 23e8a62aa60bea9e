"""Newton, tangents, pseudo-arclength continuation and fold location on a shooting problem."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import brentq


_NEWTON_TOL = 1e-10      # Newton update norm (scaled units) that counts as converged

# --------------------------------------------------------------------------------------
# Newton, tangents, pseudo-arclength continuation, fold location
# --------------------------------------------------------------------------------------

@dataclass
class _Point:
    us: np.ndarray      # scaled unknowns
    J: np.ndarray       # Jacobian of the periodicity/phase equations (scaled)
    H: np.ndarray       # samples over one period
    iters: int


def _newton(problem, us, a, uref, maxit: int = 12) -> _Point | None:
    """Solve F(u) = 0 together with a . (u - uref) = 0 (arclength or a fixed unknown)."""
    us = us.copy()
    prev = np.inf
    for it in range(1, maxit + 1):
        ev = problem.evaluate(us)
        if not np.all(np.isfinite(ev.r)) or not np.all(np.isfinite(ev.J)):
            return None
        A = np.vstack([ev.J, a])
        g = np.append(ev.r, a @ (us - uref))
        try:
            du = np.linalg.solve(A, -g)
        except np.linalg.LinAlgError:
            return None
        us += du
        step = float(np.linalg.norm(du))
        if step < _NEWTON_TOL:
            H = problem.evaluate(us, jac=False).H
            return _Point(us, ev.J, H, it)
        if it > 3 and step > 0.5 * prev:   # not converging quadratically: give up early
            return None
        prev = step
    return None


def _tangent(J: np.ndarray, t_prev: np.ndarray) -> np.ndarray:
    """Unit null vector of J oriented along t_prev."""
    A = np.vstack([J, t_prev])
    rhs = np.zeros(A.shape[0])
    rhs[-1] = 1.0
    t = np.linalg.solve(A, rhs)
    t /= np.linalg.norm(t)
    if t @ t_prev < 0:
        t = -t
    return t


@dataclass
class _Trace:
    points: list
    tangents: list
    folds: list         # indices k such that a fold lies between points k and k+1
    reason: str


def _continue(problem, first: _Point, t0: np.ndarray, *, ds: float, ds_min: float,
              ds_max: float, max_points: int, stop, min_cos: float = 0.97) -> _Trace:
    """Pseudo-arclength continuation from a converged point along tangent t0."""
    p_idx = problem.par_index
    t = _tangent(first.J, t0)
    points, tangents, folds = [first], [t], []
    reason = "max_points"
    while len(points) < max_points:
        cur = points[-1]
        pred = cur.us + ds * t
        new = _newton(problem, pred, t, pred)
        t_new = None
        if new is not None:
            t_new = _tangent(new.J, t)
            if t_new @ t < min_cos:          # turned too sharply: refine the step
                new = None
        if new is None:
            ds *= 0.5
            if ds < ds_min:
                reason = "step too small"
                break
            continue
        if t[p_idx] * t_new[p_idx] < 0:
            folds.append(len(points) - 1)
        points.append(new)
        tangents.append(t_new)
        t = t_new
        if new.iters <= 3:
            ds = min(1.5 * ds, ds_max)
        elif new.iters >= 6:
            ds = max(0.7 * ds, ds_min)
        why = stop(new.us)
        if why:
            reason = why
            break
    return _Trace(points, tangents, folds, reason)


def _locate_fold(problem, trace: _Trace, k: int) -> _Point:
    """The fold between points k and k+1: root of the tangent's parameter component."""
    p_idx = problem.par_index
    base, t = trace.points[k], trace.tangents[k]
    ds_hi = float(t @ (trace.points[k + 1].us - base.us))
    cache: dict[float, _Point] = {}

    def solve(ds):
        pred = base.us + ds * t
        pt = _newton(problem, pred, t, pred)
        if pt is None:
            raise RuntimeError("fold refinement: corrector failed")
        cache[ds] = pt
        return pt

    def g(ds):
        if ds == 0.0:
            return trace.tangents[k][p_idx]
        return _tangent(solve(ds).J, t)[p_idx]

    g_hi = trace.tangents[k + 1][p_idx]
    if np.sign(g_hi) == np.sign(g(0.0)):
        raise RuntimeError("fold refinement: no sign change")
    ds_f = brentq(lambda s: g(s) if s < ds_hi else g_hi, 0.0, ds_hi, xtol=1e-12, rtol=1e-12)
    return cache.get(ds_f) or solve(ds_f)


def _fixed_parameter_solve(problem, us_guess: np.ndarray, value_scaled: float) -> _Point | None:
    a = np.zeros(us_guess.size)
    a[problem.par_index] = 1.0
    uref = us_guess.copy()
    uref[problem.par_index] = value_scaled
    guess = us_guess.copy()
    guess[problem.par_index] = value_scaled
    return _newton(problem, guess, a, uref)


def _crossings(par: np.ndarray, value: float) -> list[int]:
    """Indices k of the segments [par[k], par[k+1]] that contain value (each crossing once)."""
    out = []
    for k in range(par.size - 1):
        d0, d1 = par[k] - value, par[k + 1] - value
        if d0 == 0.0 or d0 * d1 < 0.0 or (k == par.size - 2 and d1 == 0.0):
            out.append(k)
    return out
