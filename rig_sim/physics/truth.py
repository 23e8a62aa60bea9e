"""Ground-truth bifurcation analysis of both rigs.

The campaign tests judge a CBC measurement against *the rig's own truth*: the
periodic orbits of the very right-hand sides the firmware integrates
(``rhs.flutter_deriv`` and ``rhs.oscillator_deriv``, with the same effect
vector), traced here by numerical continuation. Nothing in this module is
fitted or tabulated; every number comes from the equations.

Method (the same for both rigs)
-------------------------------
* **Shooting.** A periodic orbit is a fixed point of the flow over one period.
  The flow is integrated by a compiled fixed-step classical Runge-Kutta scheme
  (``n_steps`` steps per period, default 1000 for the aerofoil and 600 for the
  oscillator; halving the step changes amplitudes by less than 1e-8 relative).
  Because the step count per period is fixed, the discrete flow map is smooth
  in the period and the parameter, so Newton converges quadratically on it.
* **Jacobians by central differences.** All unknowns (initial state, period,
  parameter) are perturbed by +-1e-6 in scaled units and the 2n+1
  trajectories are integrated in one compiled call; the truncation error is
  O(1e-12). The state block plus the identity is the monodromy matrix, whose
  eigenvalues are the Floquet multipliers.
* **Aerofoil (autonomous).** Unknowns (y0, T, V); equations
  ``phi_T(y0) - y0 = 0`` and the phase condition ``h'(0) = 0`` (the orbit
  starts at a heave extremum). One Floquet multiplier is always 1 (a shift
  along the orbit); it is excluded from the stability test.
* **Oscillator (forced).** Period fixed at 1/f; unknowns (y0, Phi) with the
  coil current in y0 (the hidden third state); equations ``phi_T(y0) - y0 = 0``.
* **Pseudo-arclength continuation** in scaled coordinates with a tangent
  predictor, step control by Newton effort and tangent turning angle, and
  fold detection by a sign change of the parameter component of the tangent.
  Each fold is then located to solver precision by a 1-D root find on the
  arclength step (the parameter component of the tangent is zero at a fold).
* **Amplitude metric.** "Amplitude" is always the FIRST-HARMONIC amplitude
  ``sqrt(a1^2 + b1^2)`` of the Fourier series of the coordinate over one
  period (heave h for the aerofoil, tip displacement x for the oscillator),
  computed from the uniformly spaced shooting samples (the trapezoid rule is
  spectrally accurate for periodic data). This is the metric the whole project
  uses.

Stability: an orbit is stable when every non-trivial Floquet multiplier lies
inside the unit circle (modulus < 1).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np
from numba import njit
from scipy.optimize import brentq

from .effects import EFFECT_SLOTS, parse_effects
from .flutter import FlutterParams, flutter_jacobian, flutter_kernel_params
from .oscillator import OscillatorParams, oscillator_kernel_params
from .rhs import flutter_deriv, oscillator_deriv

__all__ = [
    "FlutterBranch", "ForcedCurve", "effect_vector", "flutter_equilibrium_eigenvalues",
    "flutter_hopf", "flutter_lco_branch", "flutter_lco_at", "flutter_orbit_at",
    "oscillator_scurve", "oscillator_amplitude_at", "oscillator_orbit_at",
    "first_harmonic",
]

_FD_STEP = 1e-6          # central-difference step, in scaled units
_NEWTON_TOL = 1e-10      # Newton update norm (scaled units) that counts as converged


# --------------------------------------------------------------------------------------
# effects
# --------------------------------------------------------------------------------------

def effect_vector(rig: str, effects) -> np.ndarray:
    """The kernel's effect vector from None, a ``{name: value}`` mapping, a list of
    ``"name=value"`` strings, or an array of ``EFFECT_SLOTS`` numbers."""
    if effects is None:
        return np.zeros(EFFECT_SLOTS)
    if isinstance(effects, Mapping):
        vec, _ = parse_effects(rig, [f"{k}={v}" for k, v in effects.items()])
        return vec
    if isinstance(effects, (list, tuple)) and all(isinstance(e, str) for e in effects):
        vec, _ = parse_effects(rig, list(effects))
        return vec
    vec = np.asarray(effects, dtype=float).ravel()
    if vec.shape != (EFFECT_SLOTS,) or not np.all(np.isfinite(vec)):
        raise ValueError(f"effects: expected {EFFECT_SLOTS} finite numbers, got {vec!r}")
    return vec.copy()


# --------------------------------------------------------------------------------------
# compiled fixed-step integrators (classical RK4) for batches of trajectories
# --------------------------------------------------------------------------------------

@njit(cache=True)
def _flutter_shoot(Y0, Ks, Ts, E, n, H):
    """Integrate m aerofoil trajectories over their periods Ts with n RK4 steps each.

    Trajectory j starts at Y0[j], uses kernel parameters Ks[j] (its airspeed) and
    lasts Ts[j]. Returns the end states; H (n, 6) receives trajectory 0's states at
    the n uniformly spaced times k T/n, k = 0..n-1.
    """
    m = Y0.shape[0]
    out = np.empty_like(Y0)
    y = np.empty(6)
    tmp = np.empty(6)
    k1 = np.empty(6)
    k2 = np.empty(6)
    k3 = np.empty(6)
    k4 = np.empty(6)
    for j in range(m):
        K = Ks[j]
        dt = Ts[j] / n
        for i in range(6):
            y[i] = Y0[j, i]
        for s in range(n):
            if j == 0:
                for i in range(6):
                    H[s, i] = y[i]
            flutter_deriv(y, k1, 0.0, 0.0, K, E)
            for i in range(6):
                tmp[i] = y[i] + 0.5 * dt * k1[i]
            flutter_deriv(tmp, k2, 0.0, 0.0, K, E)
            for i in range(6):
                tmp[i] = y[i] + 0.5 * dt * k2[i]
            flutter_deriv(tmp, k3, 0.0, 0.0, K, E)
            for i in range(6):
                tmp[i] = y[i] + dt * k3[i]
            flutter_deriv(tmp, k4, 0.0, 0.0, K, E)
            for i in range(6):
                y[i] += dt / 6.0 * (k1[i] + 2.0 * k2[i] + 2.0 * k3[i] + k4[i])
        for i in range(6):
            out[j, i] = y[i]
    return out


@njit
def _flutter_shoot_plugin(Y0, Ks, Ts, E, n, H, force, scale):
    """As :func:`_flutter_shoot`, with a compiled plugin force(t, q, qdot, None) -> (F_h,
    M_alpha) added at every stage (times it by ``scale``; t = 0: the plugin must not
    depend on time, the aerofoil being autonomous). Not cached: a compiled function is an
    argument."""
    m = Y0.shape[0]
    out = np.empty_like(Y0)
    y = np.empty(6)
    tmp = np.empty(6)
    ks = np.empty((4, 6))
    for j in range(m):
        K = Ks[j]
        dt = Ts[j] / n
        for i in range(6):
            y[i] = Y0[j, i]
        for s in range(n):
            if j == 0:
                for i in range(6):
                    H[s, i] = y[i]
            for st in range(4):
                if st == 0:
                    for i in range(6):
                        tmp[i] = y[i]
                else:
                    c = dt if st == 3 else 0.5 * dt
                    for i in range(6):
                        tmp[i] = y[i] + c * ks[st - 1, i]
                f = force(0.0, tmp[0:2].copy(), tmp[3:5].copy(), None)
                flutter_deriv(tmp, ks[st], scale * f[0], scale * f[1], K, E)
            for i in range(6):
                y[i] += dt / 6.0 * (ks[0, i] + 2.0 * ks[1, i] + 2.0 * ks[2, i] + ks[3, i])
        for i in range(6):
            out[j, i] = y[i]
    return out


def compiled_plugin(func):
    """The plugin compiled for the truth's integrators (numba), or ValueError saying why
    it cannot be: the truth runs the plugin inside compiled code, so it must be plain
    numerical Python that ignores its ``params`` argument."""
    from numba import njit as _njit
    f = _njit(func)
    try:
        out = np.asarray(f(0.0, np.zeros(2), np.zeros(2), None), dtype=float)
    except Exception as exc:  # noqa: BLE001 - numba's typing errors are many kinds
        raise ValueError(f"the plugin cannot be compiled for the truth analysis "
                         f"({type(exc).__name__})") from None
    if out.shape != (2,):
        raise ValueError("the plugin must return (heave force, pitch moment)")
    return f


@njit(cache=True)
def _oscillator_shoot(Y0, Phis, omega, K, E, mass, n, H):
    """Integrate m forced-oscillator trajectories over one forcing period 2 pi/omega.

    Trajectory j starts at Y0[j] at t = 0 under base acceleration
    Phis[j] cos(omega t). H (n, 3) receives trajectory 0's states at t = k T/n.
    """
    m = Y0.shape[0]
    out = np.empty_like(Y0)
    y = np.empty(3)
    tmp = np.empty(3)
    k1 = np.empty(3)
    k2 = np.empty(3)
    k3 = np.empty(3)
    k4 = np.empty(3)
    dt = 2.0 * np.pi / omega / n
    for j in range(m):
        phi = Phis[j]
        for i in range(3):
            y[i] = Y0[j, i]
        for s in range(n):
            if j == 0:
                for i in range(3):
                    H[s, i] = y[i]
            t = s * dt
            a0 = phi * np.cos(omega * t)
            ah = phi * np.cos(omega * (t + 0.5 * dt))
            a1 = phi * np.cos(omega * (t + dt))
            oscillator_deriv(y, k1, a0, 0.0, K, E, mass)
            for i in range(3):
                tmp[i] = y[i] + 0.5 * dt * k1[i]
            oscillator_deriv(tmp, k2, ah, 0.0, K, E, mass)
            for i in range(3):
                tmp[i] = y[i] + 0.5 * dt * k2[i]
            oscillator_deriv(tmp, k3, ah, 0.0, K, E, mass)
            for i in range(3):
                tmp[i] = y[i] + dt * k3[i]
            oscillator_deriv(tmp, k4, a1, 0.0, K, E, mass)
            for i in range(3):
                y[i] += dt / 6.0 * (k1[i] + 2.0 * k2[i] + 2.0 * k3[i] + k4[i])
        for i in range(3):
            out[j, i] = y[i]
    return out


def first_harmonic(samples: np.ndarray) -> tuple[float, float, float]:
    """(amplitude, a1, b1) of the first Fourier harmonic of n uniform samples over one
    period (sample k at phase 2 pi k/n): x ~ a0 + a1 cos + b1 sin."""
    x = np.asarray(samples, dtype=float)
    n = x.shape[0]
    ph = 2.0 * np.pi * np.arange(n) / n
    a1 = 2.0 / n * float(np.dot(x, np.cos(ph)))
    b1 = 2.0 / n * float(np.dot(x, np.sin(ph)))
    return math.hypot(a1, b1), a1, b1


# --------------------------------------------------------------------------------------
# shooting problems (residual + Jacobian in scaled coordinates)
# --------------------------------------------------------------------------------------

@dataclass
class _Eval:
    r: np.ndarray                 # residual (scaled)
    J: np.ndarray | None          # Jacobian wrt scaled unknowns
    H: np.ndarray                 # base trajectory samples over one period


class _FlutterProblem:
    """Periodic orbits of the autonomous aerofoil: unknowns u = (y0[6], T, V)."""

    dim_state = 6
    par_index = 7

    def __init__(self, params: FlutterParams, E: np.ndarray, n_steps: int, su: np.ndarray,
                 plugin=None, plugin_scale: float = 1.0):
        self.p = params
        self.E = E
        self.n = int(n_steps)
        self.su = su
        self.plugin = plugin
        self.plugin_scale = float(plugin_scale)
        self._kcache: dict[float, np.ndarray] = {}

    def _K(self, V: float) -> np.ndarray:
        K = self._kcache.get(V)
        if K is None:
            if len(self._kcache) > 64:
                self._kcache.clear()
            K = flutter_kernel_params(self.p, V)
            self._kcache[V] = K
        return K

    def _residual(self, y0, y1):
        sy = self.su[:6]
        r = np.empty(7)
        r[:6] = (y1 - y0) / sy
        r[6] = y0[3] / sy[3]
        return r

    def evaluate(self, us: np.ndarray, jac: bool = True) -> _Eval:
        u = us * self.su
        nu = 8
        m = 1 + 2 * nu if jac else 1
        U = np.tile(u, (m, 1))
        if jac:
            for j in range(nu):
                U[1 + 2 * j, j] += _FD_STEP * self.su[j]
                U[2 + 2 * j, j] -= _FD_STEP * self.su[j]
        Ks = np.array([self._K(float(row[7])) for row in U])
        H = np.empty((self.n, 6))
        if self.plugin is None:
            Y1 = _flutter_shoot(np.ascontiguousarray(U[:, :6]), Ks,
                                np.ascontiguousarray(U[:, 6]), self.E, self.n, H)
        else:
            Y1 = _flutter_shoot_plugin(np.ascontiguousarray(U[:, :6]), Ks,
                                       np.ascontiguousarray(U[:, 6]), self.E, self.n, H,
                                       self.plugin, self.plugin_scale)
        r = self._residual(U[0, :6], Y1[0])
        J = None
        if jac:
            J = np.empty((7, nu))
            for j in range(nu):
                rp = self._residual(U[1 + 2 * j, :6], Y1[1 + 2 * j])
                rm = self._residual(U[2 + 2 * j, :6], Y1[2 + 2 * j])
                J[:, j] = (rp - rm) / (2.0 * _FD_STEP)
        return _Eval(r, J, H)

    def floquet(self, J: np.ndarray) -> np.ndarray:
        """Floquet multipliers (similarity-transformed monodromy: same eigenvalues)."""
        return np.linalg.eigvals(J[:6, :6] + np.eye(6))


class _OscillatorProblem:
    """Forced periodic orbits of the oscillator: unknowns u = (x0, x'0, i0, Phi)."""

    dim_state = 3
    par_index = 3

    def __init__(self, params: OscillatorParams, E: np.ndarray, freq_hz: float,
                 n_steps: int, su: np.ndarray):
        self.p = params
        self.E = E
        self.omega = 2.0 * np.pi * float(freq_hz)
        self.K = oscillator_kernel_params(params)
        self.n = int(n_steps)
        self.su = su

    def evaluate(self, us: np.ndarray, jac: bool = True) -> _Eval:
        u = us * self.su
        nu = 4
        m = 1 + 2 * nu if jac else 1
        U = np.tile(u, (m, 1))
        if jac:
            for j in range(nu):
                U[1 + 2 * j, j] += _FD_STEP * self.su[j]
                U[2 + 2 * j, j] -= _FD_STEP * self.su[j]
        H = np.empty((self.n, 3))
        Y1 = _oscillator_shoot(np.ascontiguousarray(U[:, :3]), np.ascontiguousarray(U[:, 3]),
                               self.omega, self.K, self.E, self.p.mass, self.n, H)
        sy = self.su[:3]
        R = (Y1 - U[:, :3]) / sy
        J = None
        if jac:
            J = np.empty((3, nu))
            for j in range(nu):
                J[:, j] = (R[1 + 2 * j] - R[2 + 2 * j]) / (2.0 * _FD_STEP)
        return _Eval(R[0], J, H)

    def floquet(self, J: np.ndarray) -> np.ndarray:
        return np.linalg.eigvals(J[:3, :3] + np.eye(3))


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


def _crossings(par: np.ndarray, value: float) -> list[int]:
    """Indices k of the segments [par[k], par[k+1]] that contain value (each crossing once)."""
    out = []
    for k in range(par.size - 1):
        d0, d1 = par[k] - value, par[k + 1] - value
        if d0 == 0.0 or d0 * d1 < 0.0 or (k == par.size - 2 and d1 == 0.0):
            out.append(k)
    return out


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


# --------------------------------------------------------------------------------------
# oscillator: S-curve at fixed frequency
# --------------------------------------------------------------------------------------

@dataclass
class ForcedCurve:
    """Forced periodic orbits of the oscillator against base-acceleration amplitude Phi
    (m/s^2) at a fixed forcing frequency, in continuation order.

    Arrays: Phi, amp (first-harmonic displacement amplitude, m), x_max (max |x|, m),
    current_amp (first-harmonic coil current amplitude, A), floquet_max (largest
    multiplier modulus), stable, states (state (x, x', i) at t = 0, when the forcing
    Phi cos(w t) peaks). ``folds``: dicts (Phi, amp, floquet_max, state, index: the
    curve point just before the fold), each located to solver precision.
    """

    freq_hz: float
    Phi: np.ndarray
    amp: np.ndarray
    x_max: np.ndarray
    current_amp: np.ndarray
    floquet_max: np.ndarray
    stable: np.ndarray
    states: np.ndarray
    folds: list
    params: OscillatorParams
    effects: np.ndarray
    n_steps: int
    scales: np.ndarray
    termination: str = ""
    _problem: object = field(default=None, repr=False, compare=False)


def _oscillator_record(problem: _OscillatorProblem, pt: _Point) -> dict:
    u = pt.us * problem.su
    fmax = float(np.max(np.abs(problem.floquet(pt.J))))
    return dict(Phi=float(u[3]), amp=first_harmonic(pt.H[:, 0])[0],
                x_max=float(np.max(np.abs(pt.H[:, 0]))),
                current_amp=first_harmonic(pt.H[:, 2])[0],
                floquet_max=fmax, stable=bool(fmax < 1.0), state=u[:3].copy())


def oscillator_scurve(freq_hz: float, params: OscillatorParams = OscillatorParams(),
                      effects=None, *, Phi_start: float = 0.1, Phi_max: float | None = None,
                      amp_max: float = 0.05, n_steps: int = 600, ds_max: float = 0.25,
                      max_points: int = 800) -> ForcedCurve:
    """Continue the forced periodic orbits at ``freq_hz`` in the forcing amplitude Phi.

    Starts at Phi_start (m/s^2) from rest as the Newton guess (nearly linear there),
    then pseudo-arclength continuation over the 3-state system (x, x', coil current)
    with the period fixed at 1/f, through any folds, until Phi exceeds Phi_max
    (default: the shaker limit), Phi turns negative, the amplitude exceeds amp_max (m)
    or max_points orbits are traced. Scaled unknowns: x by 1 mm, x' by w x 1 mm,
    current by the linear coil response to 1 mm, Phi by 5 m/s^2.
    """
    E = effect_vector("oscillator", effects)
    if Phi_max is None:
        Phi_max = params.shaker_limit
    omega = 2.0 * np.pi * freq_hz
    sx = 1e-3
    si = params.theta * omega * sx / math.hypot(params.R, omega * params.L)
    su = np.array([sx, omega * sx, si, 5.0])
    problem = _OscillatorProblem(params, E, freq_hz, n_steps, su)
    first = _fixed_parameter_solve(problem, np.zeros(4), Phi_start / su[3])
    if first is None:
        raise RuntimeError(f"oscillator_scurve: no orbit at Phi = {Phi_start} ({freq_hz} Hz)")
    t0 = np.zeros(4)
    t0[3] = 1.0

    def stop(us):
        u = us * su
        if u[3] > Phi_max:
            return "Phi above Phi_max"
        if u[3] < 0:
            return "Phi below zero"
        if abs(u[0]) > amp_max:
            return "amplitude above amp_max"
        return ""

    tr = _continue(problem, first, t0, ds=0.05, ds_min=1e-7, ds_max=ds_max,
                   max_points=max_points, stop=stop)
    recs = [_oscillator_record(problem, pt) for pt in tr.points]
    folds = []
    for k in tr.folds:
        rec = _oscillator_record(problem, _locate_fold(problem, tr, k))
        folds.append(dict(Phi=rec["Phi"], amp=rec["amp"], floquet_max=rec["floquet_max"],
                          index=k, state=rec["state"]))

    def col(name, dtype=float):
        return np.array([r[name] for r in recs], dtype=dtype)

    return ForcedCurve(
        freq_hz=float(freq_hz), Phi=col("Phi"), amp=col("amp"), x_max=col("x_max"),
        current_amp=col("current_amp"), floquet_max=col("floquet_max"),
        stable=col("stable", bool), states=np.array([r["state"] for r in recs]),
        folds=folds, params=params, effects=E, n_steps=n_steps, scales=su,
        termination=tr.reason, _problem=problem)


def oscillator_orbit_at(Phi: float, curve: ForcedCurve) -> list[dict]:
    """Every orbit of ``curve`` at forcing amplitude Phi, re-solved by Newton at exactly
    Phi, sorted by amplitude. Each entry: amp, x_max, current_amp, floquet_max, stable,
    state."""
    problem = curve._problem
    out = []
    for k in _crossings(curve.Phi, Phi):
        P0, P1 = curve.Phi[k], curve.Phi[k + 1]
        w = 0.0 if P1 == P0 else (Phi - P0) / (P1 - P0)
        u = np.append((1 - w) * curve.states[k] + w * curve.states[k + 1], Phi)
        pt = _fixed_parameter_solve(problem, u / problem.su, Phi / problem.su[3])
        if pt is None:
            raise RuntimeError(f"oscillator_orbit_at: Newton failed at Phi = {Phi}")
        out.append(_oscillator_record(problem, pt))
    out.sort(key=lambda r: r["amp"])
    return out


def oscillator_amplitude_at(Phi: float, curve: ForcedCurve) -> list[tuple[float, bool]]:
    """[(first-harmonic amplitude in m, stable), ...] of all branches at Phi, smallest
    first (three entries between the folds of an S-curve, one outside)."""
    return [(r["amp"], r["stable"]) for r in oscillator_orbit_at(Phi, curve)]
