"""The aerofoil's truth: equilibrium, Hopf point and the limit-cycle branch."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import brentq

from ..flutter import FlutterParams, flutter_jacobian, flutter_kernel_params
from ..rhs import flutter_deriv
from .continuation import (_continue, _crossings, _fixed_parameter_solve, _locate_fold, _newton,
                           _Point, _Trace)
from .shooting import _FlutterProblem, compiled_plugin, effect_vector, first_harmonic

# --------------------------------------------------------------------------------------
# aerofoil: equilibrium and Hopf point
# --------------------------------------------------------------------------------------

def _flutter_numeric_jacobian(params: FlutterParams, V: float, E: np.ndarray) -> np.ndarray:
    """Jacobian of rhs.flutter_deriv at the rest state (central differences).

    The right-hand side vanishes at rest, so a tiny step (1e-10) loses nothing to
    cancellation and keeps the error of merely-C1 terms (|v| v damping) at ~1e-10.
    """
    K = flutter_kernel_params(params, V)
    J = np.empty((6, 6))
    dp, dm = np.empty(6), np.empty(6)
    for j in range(6):
        e = np.zeros(6)
        h = 1e-10
        e[j] = h
        flutter_deriv(e, dp, 0.0, 0.0, K, E)
        flutter_deriv(-e, dm, 0.0, 0.0, K, E)
        J[:, j] = (dp - dm) / (2 * h)
    return J


def flutter_equilibrium_eigenvalues(V: float, params: FlutterParams = FlutterParams(),
                                    effects=None) -> np.ndarray:
    """Eigenvalues of the linearisation about rest (h = alpha = w = 0) at airspeed V.

    Without effects this is ``flutter_jacobian`` (the analytic matrices); with effects
    the Jacobian of the compiled right-hand side is taken numerically, since e.g.
    freeplay removes the linear pitch spring near rest and friction adds damping.
    """
    E = effect_vector("flutter", effects)
    J = (flutter_jacobian(params, V) if not np.any(E)
         else _flutter_numeric_jacobian(params, V, E))
    return np.linalg.eigvals(J)


def _max_real(V, params, effects):
    return float(np.max(flutter_equilibrium_eigenvalues(V, params, effects).real))


def flutter_hopf(params: FlutterParams = FlutterParams(), effects=None,
                 V_range: tuple[float, float] = (2.0, 60.0)) -> tuple[float, float]:
    """(V_hopf in m/s, f_hopf in Hz): the lowest airspeed at which rest loses stability.

    Scans the largest real part of the linearisation's eigenvalues on a 0.25 m/s grid,
    then finds its root with Brent's method (to 1e-12 m/s); the frequency is the
    imaginary part of the critical pair there. Raises ValueError if rest stays stable
    (or is unstable already) over ``V_range``.
    """
    Vs = np.arange(V_range[0], V_range[1] + 1e-9, 0.25)
    g = np.array([_max_real(V, params, effects) for V in Vs])
    if g[0] >= 0:
        raise ValueError(f"flutter_hopf: rest is already unstable at V = {Vs[0]} m/s")
    idx = np.nonzero(g >= 0)[0]
    if idx.size == 0:
        raise ValueError(f"flutter_hopf: no Hopf point for V in {V_range} m/s")
    i = idx[0]
    Vh = brentq(_max_real, Vs[i - 1], Vs[i], args=(params, effects), xtol=1e-12, rtol=1e-14)
    ev = flutter_equilibrium_eigenvalues(Vh, params, effects)
    lam = ev[np.argmax(ev.real)]
    return float(Vh), float(abs(lam.imag) / (2.0 * np.pi))


# --------------------------------------------------------------------------------------
# aerofoil: limit-cycle branch
# --------------------------------------------------------------------------------------

@dataclass
class FlutterBranch:
    """Periodic orbits of the aerofoil against airspeed, in continuation order.

    Arrays (one entry per orbit): V (m/s), period (s), heave_amp and pitch_amp
    (first-harmonic amplitudes, m and rad), heave_max (max |h| over the orbit, m,
    from the shooting samples), heave_dc (mean heave, m), floquet_max (largest
    modulus among the non-trivial multipliers), stable (floquet_max < 1) and
    states (the orbit's state at phase 0, where h' = 0: shape (N, 6)).
    ``folds`` lists each fold, located to solver precision, as a dict (V, heave_amp,
    pitch_amp, period, floquet_max, state, index: the branch point just before it).
    ``hopf`` is (V, f_Hz).
    """

    V: np.ndarray
    period: np.ndarray
    heave_amp: np.ndarray
    pitch_amp: np.ndarray
    heave_max: np.ndarray
    heave_dc: np.ndarray
    floquet_max: np.ndarray
    stable: np.ndarray
    states: np.ndarray
    folds: list
    hopf: tuple
    params: FlutterParams
    effects: np.ndarray
    n_steps: int
    scales: np.ndarray
    termination: str = ""
    _problem: object = field(default=None, repr=False, compare=False)


def _flutter_orbit_record(problem: _FlutterProblem, pt: _Point) -> dict:
    u = pt.us * problem.su
    mult = problem.floquet(pt.J)
    trivial = np.argmin(np.abs(mult - 1.0))
    others = np.delete(mult, trivial)
    fmax = float(np.max(np.abs(others)))
    return dict(
        V=float(u[7]), period=float(u[6]),
        heave_amp=first_harmonic(pt.H[:, 0])[0], pitch_amp=first_harmonic(pt.H[:, 1])[0],
        heave_max=float(np.max(np.abs(pt.H[:, 0]))), heave_dc=float(np.mean(pt.H[:, 0])),
        floquet_max=fmax, stable=bool(fmax < 1.0), state=u[:6].copy(),
    )


def flutter_lco_branch(params: FlutterParams = FlutterParams(), effects=None, *,
                       V_min: float = 5.0, V_max: float = 26.0, amp_max: float = 0.5,
                       n_steps: int = 1000, ds_max: float = 0.08, max_points: int = 600,
                       start_amp: float = 0.002, start_V: float | None = None,
                       plugin=None) -> FlutterBranch:
    """Continue the aerofoil's limit cycles in airspeed from the Hopf point.

    The first orbit is found near the Hopf point from the critical eigenvector
    (heave amplitude ``start_amp``, phase h'(0) = 0), solving with h(0) fixed and
    V free; from there pseudo-arclength continuation follows the branch (for the
    subcritical aerofoil: unstable orbits towards lower V, the fold, then the
    stable large orbits towards higher V) until V leaves [V_min, V_max], the heave
    amplitude exceeds ``amp_max`` (m) or ``max_points`` orbits are traced.
    Scaled unknowns: states by the Hopf eigenvector normalised to 0.1 m heave,
    period by the Hopf period, V by 1 m/s; ``ds_max`` is the largest arclength
    step in those units.

    Effects that change rest itself (pitch freeplay leaves the pitch spring slack at
    rest; strong Coulomb friction locks it) leave no usable Hopf point. Give
    ``start_V`` then: the branch starts from the effect-free rig's stable orbit at
    that airspeed, the effects are switched on gradually at fixed airspeed (Newton at
    each step), and the branch is continued from there towards lower and higher
    airspeed (``hopf`` is then (nan, nan)). A user ``plugin`` force (the rig's
    ``--effect-plugin`` callable, time-invariant and compilable, see
    :func:`compiled_plugin`) is integrated with the rest; the Hopf point is that of the
    rig without it, so a plugin that acts at rest to first order needs ``start_V``.
    """
    E = effect_vector("flutter", effects)
    force = None if plugin is None else compiled_plugin(plugin)
    if start_V is not None:
        return _flutter_branch_from_clean(params, E, start_V, V_min=V_min, V_max=V_max,
                                          amp_max=amp_max, n_steps=n_steps, ds_max=ds_max,
                                          max_points=max_points, plugin=force)
    Vh, fh = flutter_hopf(params, E)
    if np.any(E):
        Jl = _flutter_numeric_jacobian(params, Vh, E)
    else:
        Jl = flutter_jacobian(params, Vh)
    ev, vecs = np.linalg.eig(Jl)
    i = int(np.argmin(np.abs(ev - 2j * np.pi * fh)))
    v = vecs[:, i] / vecs[0, i]          # heave component 1: h(t) = Re(v e^{i w t}) = cos
    T0 = 1.0 / fh
    sy = np.maximum(np.abs(v) * 0.1, 1e-4)
    su = np.concatenate([sy, [T0, 1.0]])
    problem = _FlutterProblem(params, E, n_steps, su, force)

    u0 = np.concatenate([start_amp * v.real, [T0, Vh]])
    us0 = u0 / su
    a = np.zeros(8)
    a[0] = 1.0
    first = _newton(problem, us0, a, us0)
    if first is None:
        raise RuntimeError("flutter_lco_branch: no periodic orbit found near the Hopf point")
    t0 = np.zeros(8)
    t0[0] = 1.0                          # leave the Hopf point with growing heave

    def stop(us):
        u = us * su
        if u[7] < V_min:
            return "V below V_min"
        if u[7] > V_max:
            return "V above V_max"
        if abs(u[0]) > amp_max:
            return "amplitude above amp_max"
        return ""

    tr = _continue(problem, first, t0, ds=0.02, ds_min=1e-7, ds_max=ds_max,
                   max_points=max_points, stop=stop)
    recs = [_flutter_orbit_record(problem, pt) for pt in tr.points]
    folds = []
    for k in tr.folds:
        fp = _locate_fold(problem, tr, k)
        rec = _flutter_orbit_record(problem, fp)
        folds.append(dict(V=rec["V"], heave_amp=rec["heave_amp"], pitch_amp=rec["pitch_amp"],
                          period=rec["period"], floquet_max=rec["floquet_max"], index=k,
                          state=rec["state"]))

    def col(name, dtype=float):
        return np.array([r[name] for r in recs], dtype=dtype)

    return FlutterBranch(
        V=col("V"), period=col("period"), heave_amp=col("heave_amp"),
        pitch_amp=col("pitch_amp"), heave_max=col("heave_max"), heave_dc=col("heave_dc"),
        floquet_max=col("floquet_max"), stable=col("stable", bool),
        states=np.array([r["state"] for r in recs]), folds=folds, hopf=(Vh, fh),
        params=params, effects=E, n_steps=n_steps, scales=su, termination=tr.reason,
        _problem=problem)


def _flutter_branch_from_clean(params, E, start_V, *, V_min, V_max, amp_max, n_steps,
                               ds_max, max_points, plugin=None) -> FlutterBranch:
    clean = flutter_lco_branch(params, None, V_min=V_min, V_max=max(V_max, start_V + 1.0),
                               amp_max=amp_max, n_steps=n_steps, ds_max=ds_max,
                               max_points=max_points)
    orbs = [o for o in flutter_orbit_at(start_V, clean) if o["stable"]]
    if not orbs:
        raise RuntimeError(f"flutter_lco_branch: the effect-free rig has no stable orbit "
                           f"at start_V = {start_V} m/s")
    orb = max(orbs, key=lambda o: o["heave_amp"])
    su = clean.scales.copy()
    us = np.concatenate([orb["state"], [orb["period"], start_V]]) / su
    a = np.zeros(8)
    a[7] = 1.0
    pt = None
    for frac in np.linspace(0.1, 1.0, 10):          # switch the effects on gradually
        problem = _FlutterProblem(params, frac * E, n_steps, su, plugin, frac)
        pt = _newton(problem, us, a, us)
        if pt is None:
            raise RuntimeError(f"flutter_lco_branch: lost the orbit at {frac:.0%} of the "
                               f"effects at V = {start_V} m/s")
        us = pt.us

    seen = [0]

    def stop(us):
        u = us * su
        if u[7] < V_min:
            return "V below V_min"
        if u[7] > V_max:
            return "V above V_max"
        if abs(u[0]) > amp_max:
            return "amplitude above amp_max"
        seen[0] += 1
        if seen[0] > 10 and np.linalg.norm(us - pt.us) < 0.5 * ds_max:
            return "closed curve"           # back at the start: the branch is a loop
        return ""

    legs = []
    for sign in (-1.0, 1.0):
        t0 = np.zeros(8)
        t0[7] = sign
        seen[0] = 0
        legs.append(_continue(problem, pt, t0, ds=0.02, ds_min=1e-7, ds_max=ds_max,
                              max_points=max_points // 2, stop=stop))
        if legs[-1].reason == "closed curve":
            legs.append(_Trace([pt], [legs[-1].tangents[0]], [], "closed curve"))
            break
    down, up = legs
    pts = down.points[::-1] + up.points[1:]
    recs = [_flutter_orbit_record(problem, p) for p in pts]
    folds = []
    for leg, offset in ((down, None), (up, len(down.points) - 1)):
        for k in leg.folds:
            try:
                fp = _locate_fold(problem, leg, k)
            except (RuntimeError, ValueError):
                fp = leg.points[k]          # a kink, not a smooth fold: the nearest orbit
            rec = _flutter_orbit_record(problem, fp)
            index = (len(down.points) - 2 - k) if offset is None else offset + k
            folds.append(dict(V=rec["V"], heave_amp=rec["heave_amp"],
                              pitch_amp=rec["pitch_amp"], period=rec["period"],
                              floquet_max=rec["floquet_max"], index=index,
                              state=rec["state"]))
    folds.sort(key=lambda f: f["index"])

    def col(name, dtype=float):
        return np.array([r[name] for r in recs], dtype=dtype)

    return FlutterBranch(
        V=col("V"), period=col("period"), heave_amp=col("heave_amp"),
        pitch_amp=col("pitch_amp"), heave_max=col("heave_max"), heave_dc=col("heave_dc"),
        floquet_max=col("floquet_max"), stable=col("stable", bool),
        states=np.array([r["state"] for r in recs]), folds=folds, hopf=(np.nan, np.nan),
        params=params, effects=E, n_steps=n_steps, scales=su,
        termination=f"{down.reason} / {up.reason}", _problem=problem)


def flutter_orbit_at(V: float, branch: FlutterBranch) -> list[dict]:
    """Every orbit of ``branch`` at airspeed V, each re-solved by Newton at exactly V
    (guess: linear interpolation between the bracketing branch points). Each entry:
    heave_amp, pitch_amp, heave_max, period, floquet_max, stable, state."""
    problem = branch._problem
    out = []
    for k in _crossings(branch.V, V):
        V0, V1 = branch.V[k], branch.V[k + 1]
        w = 0.0 if V1 == V0 else (V - V0) / (V1 - V0)
        u = np.concatenate([(1 - w) * branch.states[k] + w * branch.states[k + 1],
                            [(1 - w) * branch.period[k] + w * branch.period[k + 1], V]])
        pt = _fixed_parameter_solve(problem, u / problem.su, V / problem.su[7])
        if pt is None:
            raise RuntimeError(f"flutter_orbit_at: Newton failed at V = {V}")
        out.append(_flutter_orbit_record(problem, pt))
    return out


def flutter_lco_at(V: float, branch: FlutterBranch) -> dict:
    """{"stable": heave amplitude or None, "unstable": amplitude or None} at airspeed V.

    Amplitudes are first-harmonic heave amplitudes (m) of the orbits solved at exactly
    V (so as accurate as the shooting itself, ~1e-8 relative). If the branch has more
    than one orbit of a kind at V, the largest is returned.
    """
    res = {"stable": None, "unstable": None}
    for rec in flutter_orbit_at(V, branch):
        key = "stable" if rec["stable"] else "unstable"
        if res[key] is None or rec["heave_amp"] > res[key]:
            res[key] = rec["heave_amp"]
    return res


