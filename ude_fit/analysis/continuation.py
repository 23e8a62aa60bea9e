"""Bifurcation analysis of any fitted model: equilibria, Hopf points, branches of
periodic orbits with Floquet stability, and folds.

Method
------
* Periodic orbits by single shooting over one period (``_flow.rk4_orbit``).
  Aerofoil (autonomous): unknowns ``(y0, T, V)``, equations
  ``phi_T(y0) - y0 = 0`` and the phase condition ``h'(0) = 0``. Oscillator
  (forced at fixed frequency): unknowns ``(y0, A)``, ``phi_T(y0) - y0 = 0``.
* Jacobians by forward-mode autodiff through the integrator; the state block
  plus the identity is the monodromy matrix (its eigenvalues are the Floquet
  multipliers). For the aerofoil one multiplier is 1 and is left out.
* Pseudo-arclength continuation in scaled unknowns, step control by Newton
  effort and tangent turning; a fold is a sign change of the parameter
  component of the tangent, located by a root search on the arclength step.
* The aerofoil's branch starts at the Hopf point of the equilibrium branch
  (eigenvalues of the Jacobian, root of the largest real part in V), with two
  solves at small fixed heave amplitude. The oscillator's starts at a small
  forcing amplitude, where the response is nearly linear.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from scipy.optimize import brentq

from .._fourier import first_harmonic_amplitude
from .._systems import system_kind
from ..models.flow import rk4_orbit
from ..models.mechanistic import Drive
from ..models.equilibria import Equilibria, _equilibrium_scan, equilibrium_branch, hopf_point  # noqa: F401
from ..models.ude import UDE


_NEWTON_TOL = 1e-10


# ---------------------------------------------------------------------------------------
# compiled kernels (the model is an argument, so one compilation serves every model of
# the same structure)
# ---------------------------------------------------------------------------------------

@eqx.filter_jit
def _autonomous_eval(model, us, su, n: int):
    ns = model.n_state

    def F(us):
        u = us * su
        y0, T, V = u[:ns], u[ns], u[ns + 1]
        yT, ys = rk4_orbit(model, y0, T, Drive.of(V), n)
        r = jnp.concatenate([(yT - y0) / su[:ns], y0[model.mech.n_dof:model.mech.n_dof + 1]
                             / su[model.mech.n_dof:model.mech.n_dof + 1]])
        return r, (r, ys)

    J, (r, ys) = jax.jacfwd(F, has_aux=True)(us)
    return r, J, ys


@eqx.filter_jit
def _forced_eval(model, us, su, omega, n: int):
    ns = model.n_state

    def F(us):
        u = us * su
        y0, A = u[:ns], u[ns]
        T = 2 * jnp.pi / omega
        yT, ys = rk4_orbit(model, y0, T, Drive.harmonic(A, omega), n)
        r = (yT - y0) / su[:ns]
        return r, (r, ys)

    J, (r, ys) = jax.jacfwd(F, has_aux=True)(us)
    return r, J, ys


# ---------------------------------------------------------------------------------------
# problem wrappers (host side)
# ---------------------------------------------------------------------------------------

@dataclass
class _Eval:
    r: np.ndarray
    J: np.ndarray
    ys: np.ndarray


class _Autonomous:
    kind = "autonomous"

    def __init__(self, model: UDE, su: np.ndarray, n: int):
        self.model, self.su, self.n = model, np.asarray(su, float), n
        self.ns = model.n_state
        self.par_index = self.ns + 1

    def evaluate(self, us) -> _Eval:
        r, J, ys = _autonomous_eval(self.model, jnp.asarray(us), jnp.asarray(self.su), self.n)
        return _Eval(np.asarray(r), np.asarray(J), np.asarray(ys))

    def multipliers(self, J: np.ndarray) -> np.ndarray:
        mu = np.linalg.eigvals(J[:self.ns, :self.ns] + np.eye(self.ns))
        # drop the trivial multiplier (shift along the orbit), the one nearest 1
        k = int(np.argmin(np.abs(mu - 1.0)))
        return np.delete(mu, k)

    def unpack(self, us):
        u = np.asarray(us) * self.su
        return u[:self.ns], u[self.ns], u[self.ns + 1]


class _Forced:
    kind = "forced"

    def __init__(self, model: UDE, su: np.ndarray, omega: float, n: int):
        self.model, self.su, self.omega, self.n = model, np.asarray(su, float), float(omega), n
        self.ns = model.n_state
        self.par_index = self.ns

    def evaluate(self, us) -> _Eval:
        r, J, ys = _forced_eval(self.model, jnp.asarray(us), jnp.asarray(self.su),
                                jnp.asarray(self.omega), self.n)
        return _Eval(np.asarray(r), np.asarray(J), np.asarray(ys))

    def multipliers(self, J: np.ndarray) -> np.ndarray:
        return np.linalg.eigvals(J[:self.ns, :self.ns] + np.eye(self.ns))

    def unpack(self, us):
        u = np.asarray(us) * self.su
        return u[:self.ns], 2 * np.pi / self.omega, u[self.ns]


@dataclass
class _Point:
    us: np.ndarray
    J: np.ndarray
    ys: np.ndarray
    iters: int


def _newton(problem, us, a, uref, maxit: int = 15):
    """Solve F(u) = 0 with the extra row a . (u - uref) = 0."""
    us = np.array(us, dtype=float)
    prev = np.inf
    for it in range(1, maxit + 1):
        ev = problem.evaluate(us)
        if not (np.all(np.isfinite(ev.r)) and np.all(np.isfinite(ev.J))):
            return None
        A = np.vstack([ev.J, a])
        g = np.append(ev.r, a @ (us - uref))
        try:
            du = np.linalg.solve(A, -g)
        except np.linalg.LinAlgError:
            return None
        if not np.all(np.isfinite(du)):
            return None
        us = us + du
        step = float(np.linalg.norm(du))
        if step < _NEWTON_TOL * max(1.0, float(np.linalg.norm(us))):
            ev = problem.evaluate(us)
            return _Point(us, ev.J, ev.ys, it)
        if it > 4 and step > 0.5 * prev:
            return None
        prev = step
    return None


def _tangent(J, t_prev):
    A = np.vstack([J, t_prev])
    rhs = np.zeros(A.shape[0])
    rhs[-1] = 1.0
    t = np.linalg.solve(A, rhs)
    t /= np.linalg.norm(t)
    return t if t @ t_prev >= 0 else -t


# ---------------------------------------------------------------------------------------
# results
# ---------------------------------------------------------------------------------------

@dataclass
class Branch:
    """A traced branch of periodic orbits (numpy arrays, one entry per point)."""
    system: str
    param: np.ndarray           # airspeed (m/s) or forcing amplitude (m/s^2)
    amplitude: np.ndarray       # first-harmonic amplitude of coordinate 0 (m)
    period: np.ndarray          # s
    stable: np.ndarray          # bool
    max_multiplier: np.ndarray  # largest non-trivial |Floquet multiplier|
    y0: np.ndarray              # (n, n_state) initial states (phase: h' = 0 for the aerofoil)
    folds: list = field(default_factory=list)   # dicts: param, amplitude, period
    hopf: dict | None = None    # aerofoil: {"param", "frequency"}; None if none found
    omega: float | None = None  # oscillator: forcing angular frequency
    reason: str = ""            # why the tracing stopped

    def to_dict(self) -> dict:
        d = {}
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            d[f.name] = v.tolist() if isinstance(v, np.ndarray) else v
        return d

    @staticmethod
    def from_dict(d: dict) -> "Branch":
        arrays = {"param", "amplitude", "period", "stable", "max_multiplier", "y0"}
        kw = {k: (np.asarray(v) if k in arrays else v) for k, v in d.items()}
        kw["stable"] = kw["stable"].astype(bool)
        return Branch(**kw)

    def amplitudes_at(self, p: float) -> list[tuple[float, bool]]:
        """Every (amplitude, stable) where the branch crosses parameter ``p`` (linear interpolation)."""
        out = []
        par, amp = self.param, self.amplitude
        for k in range(len(par) - 1):
            lo, hi = par[k], par[k + 1]
            if (lo - p) * (hi - p) <= 0 and lo != hi:
                w = (p - lo) / (hi - lo)
                if w == 1.0 and k + 2 < len(par):
                    continue    # counted as w == 0 of the next segment
                a = (1 - w) * amp[k] + w * amp[k + 1]
                s = bool(self.stable[k] if w < 0.5 else self.stable[k + 1])
                out.append((float(a), s))
        return out


# ---------------------------------------------------------------------------------------
# continuation driver
# ---------------------------------------------------------------------------------------

def _record(problem, pt: _Point) -> dict:
    y0, T, p = problem.unpack(pt.us)
    mu = problem.multipliers(pt.J)
    mm = float(np.max(np.abs(mu))) if mu.size else 0.0
    return {"param": float(p), "amplitude": first_harmonic_amplitude(pt.ys[:, 0]),
            "period": float(T), "stable": mm < 1.0, "max_multiplier": mm, "y0": np.asarray(y0)}


def _continue(problem, first: _Point, t0, *, ds, ds_min, ds_max, max_points, stop,
              min_cos=0.95):
    p_idx = problem.par_index
    t = _tangent(first.J, t0)
    pts, tans, folds = [first], [t], []
    reason = "max_points"
    while len(pts) < max_points:
        pred = pts[-1].us + ds * t
        new = _newton(problem, pred, t, pred)
        t_new = None
        if new is not None:
            t_new = _tangent(new.J, t)
            if t_new @ t < min_cos:
                new = None
        if new is None:
            ds *= 0.5
            if ds < ds_min:
                reason = "step too small"
                break
            continue
        if t[p_idx] * t_new[p_idx] < 0:
            folds.append(len(pts) - 1)
        pts.append(new)
        tans.append(t_new)
        if len(pts) > 3 and _passes(pts[-2].us, new.us, first.us) and t_new @ tans[0] > 0:
            # back where it started, heading the same way: a closed curve (an isola, or a
            # loop), traced once; going on would find every fold again on each lap
            reason = "closed loop"
            break
        t = t_new
        if new.iters <= 3:
            ds = min(1.4 * ds, ds_max)
        elif new.iters >= 6:
            ds = max(0.7 * ds, ds_min)
        why = stop(problem, new)
        if why:
            reason = why
            break
    return pts, tans, folds, reason


def _passes(a, b, c) -> bool:
    """Whether the step from ``a`` to ``b`` passes ``c`` (within a third of the step)."""
    d = b - a
    L2 = float(d @ d)
    if L2 == 0.0:
        return False
    w = float(np.clip((c - a) @ d / L2, 0.0, 1.0))
    return float(np.linalg.norm(a + w * d - c)) <= np.sqrt(L2) / 3


def _locate_fold(problem, pts, tans, k):
    p_idx = problem.par_index
    base, t = pts[k], tans[k]
    ds_hi = float(t @ (pts[k + 1].us - base.us))
    cache = {}

    def solve(ds):
        pred = base.us + ds * t
        pt = _newton(problem, pred, t, pred)
        if pt is None:
            raise RuntimeError("fold refinement failed")
        cache[ds] = pt
        return pt

    def g(ds):
        if ds == 0.0:
            return tans[k][p_idx]
        if ds >= ds_hi:
            return tans[k + 1][p_idx]
        return _tangent(solve(ds).J, t)[p_idx]

    ds_f = brentq(g, 0.0, ds_hi, xtol=1e-13, rtol=1e-13)
    return cache.get(ds_f) or solve(ds_f)


def _assemble(problem, system, pts, tans, folds, reason, **extra) -> Branch:
    recs = [_record(problem, p) for p in pts]
    fold_recs = []
    for k in folds:
        try:
            fp = _locate_fold(problem, pts, tans, k)
        except (RuntimeError, ValueError):
            fp = pts[k]
        r = _record(problem, fp)
        rec = {"param": r["param"], "amplitude": r["amplitude"], "period": r["period"]}
        if not any(same_fold(rec, f) for f in fold_recs):
            fold_recs.append(rec)
    col = lambda name: np.array([r[name] for r in recs])
    return Branch(system=system, param=col("param"), amplitude=col("amplitude"),
                  period=col("period"), stable=col("stable").astype(bool),
                  max_multiplier=col("max_multiplier"), y0=np.stack(col("y0")),
                  folds=fold_recs, reason=reason, **extra)


def same_fold(f: dict, g: dict, rel: float = 1e-4) -> bool:
    """Whether two fold records are one fold of the diagram (found twice: a curve traced
    past its start, or the same branch reached from two measured orbits)."""
    return (abs(f["param"] - g["param"]) <= rel * max(1.0, abs(g["param"]))
            and abs(f["amplitude"] - g["amplitude"]) <= 1e3 * rel * max(
                abs(g["amplitude"]), 1e-12))


def trace_flutter(model: UDE, *, v_range, amp_max: float, scales, n: int = 200,
                  max_points: int = 400) -> Branch:
    """Branch of limit cycles from the Hopf point, until V leaves ``v_range`` or the heave
    amplitude passes ``amp_max``. ``scales``: typical magnitudes of (h, alpha, h', alpha')."""
    hopf = hopf_point(model, v_range)
    if hopf is None:
        return Branch("flutter", *(np.zeros(0),) * 4, np.zeros(0, bool), np.zeros(0),
                      np.zeros((0, model.n_state)), hopf=None, reason="no Hopf point in range")
    ns = model.n_state
    if hopf["omega"] <= 1e-9 * max(1.0, abs(hopf["param"])):
        # a real eigenvalue crosses first (static divergence, which a fitted correction can
        # cause): no Hopf point, so no branch of limit cycles born there
        return Branch("flutter", *(np.zeros(0),) * 4, np.zeros(0, bool), np.zeros(0),
                      np.zeros((0, ns)), hopf=None,
                      reason=f"static divergence (real eigenvalue) at {hopf['param']:.4g}, "
                      "no Hopf point")
    TH = 2 * np.pi / hopf["omega"]
    su = np.concatenate([np.asarray(scales, float), [TH, max(1.0, hopf["param"])]])
    prob = _Autonomous(model, su, n)
    v = hopf["eigvec"]
    v = v / v[0]                      # heave component real: h(t) = eps cos(w t), h'(0) = 0
    pts = []
    for frac in (0.01, 0.02):
        eps = frac * scales[0]
        y0 = hopf["y"] + eps * np.real(v)
        us = np.concatenate([y0, [TH, hopf["param"]]]) / su
        a = np.zeros(ns + 2)
        a[0] = 1.0
        uref = us.copy()
        uref[0] = (hopf["y"][0] + eps) / su[0]
        pt = _newton(prob, us, a, uref)
        if pt is None:
            return Branch("flutter", *(np.zeros(0),) * 4, np.zeros(0, bool), np.zeros(0),
                          np.zeros((0, ns)), hopf=_hopf_public(hopf),
                          reason="could not start the branch at the Hopf point")
        pts.append(pt)
    t0 = pts[1].us - pts[0].us
    t0 /= np.linalg.norm(t0)

    def stop(problem, pt):
        y0, T, V = problem.unpack(pt.us)
        if not (v_range[0] <= V <= v_range[1]):
            return "airspeed out of range"
        if abs(y0[0]) > amp_max:
            return "amplitude cap"
        if not (TH / 4 < T < 4 * TH):
            return "period out of range"
        return ""

    seq, tans, folds, reason = _continue(prob, pts[1], t0, ds=0.02, ds_min=1e-5, ds_max=0.08,
                                         max_points=max_points, stop=stop)
    seq = [pts[0]] + seq
    tans = [tans[0]] + tans
    folds = [k + 1 for k in folds]
    return _assemble(prob, "flutter", seq, tans, folds, reason, hopf=_hopf_public(hopf))


def _hopf_public(h):
    return {"param": h["param"], "frequency": h["frequency"]}


def trace_forced(model: UDE, *, freq_hz: float, a_range, amp_max: float, scales,
                 n: int = 200, max_points: int = 400) -> Branch:
    """Response curve against the forcing amplitude at a fixed frequency."""
    omega = 2 * np.pi * freq_hz
    ns = model.n_state
    su = np.concatenate([np.asarray(scales, float), [max(a_range[1], 1e-9)]])
    prob = _Forced(model, su, omega, n)
    A0 = a_range[0]
    us = np.concatenate([np.zeros(ns), [A0]]) / su
    a = np.zeros(ns + 1)
    a[-1] = 1.0
    first = _newton(prob, us, a, us.copy())
    if first is None:
        return Branch("oscillator", *(np.zeros(0),) * 4, np.zeros(0, bool), np.zeros(0),
                      np.zeros((0, ns)), omega=omega, reason="no periodic response at the start")

    def stop(problem, pt):
        y0, _, A = problem.unpack(pt.us)
        if A > a_range[1]:
            return "forcing out of range"
        if A < 0:
            return "negative forcing"
        if np.max(np.abs(pt.ys[:, 0])) > amp_max:
            return "amplitude cap"
        return ""

    t0 = np.zeros(ns + 1)
    t0[-1] = 1.0
    seq, tans, folds, reason = _continue(prob, first, t0, ds=0.03, ds_min=1e-6, ds_max=0.1,
                                         max_points=max_points, stop=stop)
    return _assemble(prob, "oscillator", seq, tans, folds, reason, omega=omega)


def orbit_at(model: UDE, branch: Branch, param: float, stable: bool | None, *, scales,
             near: float | None = None, n: int = 200) -> dict | None:
    """The model's periodic orbit at ``param`` where ``branch`` crosses it with the given
    stability (None: any), the crossing nearest in amplitude to ``near``; solved exactly by
    Newton at fixed parameter from the crossing interpolated between two branch points.

    Returns {"samples" (n, n_state), "period", "amplitude", "stable"} or None when the
    branch does not cross ``param`` with that stability (or the solve fails).
    """
    par = branch.param
    cands = []
    for k in range(len(par) - 1):
        lo, hi = par[k], par[k + 1]
        if lo == hi or (lo - param) * (hi - param) > 0:
            continue
        w = (param - lo) / (hi - lo)
        s = bool(branch.stable[k] if w < 0.5 else branch.stable[k + 1])
        if stable is not None and s != stable:
            continue
        amp = (1 - w) * branch.amplitude[k] + w * branch.amplitude[k + 1]
        cands.append((abs(amp - near) if near is not None else 0.0, k, w))
    if not cands:
        return None
    _, k, w = min(cands)
    y0 = (1 - w) * branch.y0[k] + w * branch.y0[k + 1]
    T = (1 - w) * branch.period[k] + w * branch.period[k + 1]
    if system_kind(branch.system).autonomous:
        su = np.concatenate([np.asarray(scales, float), [T, max(1.0, abs(param))]])
        prob = _Autonomous(model, su, n)
        us = np.concatenate([y0, [T, param]]) / su
    else:
        su = np.concatenate([np.asarray(scales, float), [max(abs(param), 1e-9)]])
        prob = _Forced(model, su, branch.omega, n)
        us = np.concatenate([y0, [param]]) / su
    a = np.zeros(us.size)
    a[prob.par_index] = 1.0
    pt = _newton(prob, us, a, us.copy())
    if pt is None:
        return None
    rec = _record(prob, pt)
    return {"samples": pt.ys[:, :model.n_state], "period": rec["period"],
            "amplitude": rec["amplitude"], "stable": bool(rec["stable"])}


def trace_flutter_through(model: UDE, y0, T: float, V: float, *, v_range, amp_max: float,
                          scales, n: int = 200, max_points: int = 300,
                          known=None) -> Branch | None:
    """The branch through a given orbit guess (y0 with h'(0) ~ 0, period T) at airspeed V,
    continued both ways: for branches not connected to the Hopf point (isolas), which a
    fitted model can have. None if no periodic orbit is found near the guess, or if
    ``known(V, amplitude)`` says the orbit found lies on a branch already traced."""
    ns = model.n_state
    su = np.concatenate([np.asarray(scales, float), [T, max(1.0, abs(V))]])
    prob = _Autonomous(model, su, n)
    us = np.concatenate([np.asarray(y0, float), [T, V]]) / su
    a = np.zeros(ns + 2)
    a[prob.par_index] = 1.0
    first = _newton(prob, us, a, us.copy())
    if first is None:
        return None
    y1, T1, _ = prob.unpack(first.us)
    if np.max(np.abs(first.ys[:, 0])) < 1e-3 * scales[0] or not (T / 2 < T1 < 2 * T):
        return None                     # collapsed onto the equilibrium or another period
    if known is not None and known(V, first_harmonic_amplitude(first.ys[:, 0])):
        return None

    def stop(problem, pt):
        y, TT, VV = problem.unpack(pt.us)
        if not (v_range[0] <= VV <= v_range[1]):
            return "airspeed out of range"
        if abs(y[0]) > amp_max:
            return "amplitude cap"
        if np.max(np.abs(pt.ys[:, 0])) < 1e-3 * scales[0]:
            return "amplitude collapsed"
        if not (T / 4 < TT < 4 * T):
            return "period out of range"
        return ""

    t_par = np.zeros(ns + 2)
    t_par[prob.par_index] = 1.0
    halves = []
    for sign in (1.0, -1.0):
        seq, tans, folds, reason = _continue(prob, first, sign * t_par, ds=0.02, ds_min=1e-5,
                                             ds_max=0.08, max_points=max_points // 2,
                                             stop=stop)
        halves.append((seq, tans, folds, reason))
    (fs, ft, ff, fr), (bs, bt, bf, br) = halves
    if fr == "closed loop":
        # the forward half went all the way round: it is the whole isola
        return _assemble(prob, "flutter", fs, ft, ff, fr, hopf=None)
    # backward half reversed (its tangents flipped) + forward half without the shared point
    m = len(bs)
    pts = bs[::-1] + fs[1:]
    tans = [-t for t in bt[::-1]] + ft[1:]
    folds = sorted([m - 2 - k for k in bf] + [m - 1 + k for k in ff])
    return _assemble(prob, "flutter", pts, tans, folds, f"{br}; {fr}", hopf=None)
