"""Shooting: the effect vector, compiled fixed-step RK4 integrators for batches of
trajectories, and the shooting problems (residual and Jacobian in scaled coordinates)."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
from numba import njit

from ..effects import EFFECT_SLOTS, parse_effects
from ..flutter import FlutterParams, flutter_kernel_params
from ..oscillator import OscillatorParams, oscillator_kernel_params
from ..rhs import flutter_deriv, oscillator_deriv

_FD_STEP = 1e-6          # central-difference step, in scaled units


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


def compiled_plugin(func, ndof: int = 2):
    """The plugin compiled for the truth's integrators (numba), or ValueError saying why
    it cannot be: the truth runs the plugin inside compiled code, so it must be plain
    numerical Python that ignores its ``params`` argument. ``ndof``: 2 for the aerofoil
    (heave force, pitch moment), 1 for the oscillator (the force on the tip, N)."""
    from numba import njit as _njit
    f = _njit(func)
    try:
        out = np.asarray(f(0.0, np.zeros(ndof), np.zeros(ndof), None), dtype=float)
    except Exception as exc:  # noqa: BLE001 - numba's typing errors are many kinds
        raise ValueError(f"the plugin cannot be compiled for the truth analysis "
                         f"({type(exc).__name__})") from None
    if out.shape != (ndof,):
        raise ValueError("the plugin must return (heave force, pitch moment)" if ndof == 2
                         else "the plugin must return (force,)")
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


@njit
def _oscillator_shoot_plugin(Y0, Phis, omega, K, E, mass, n, H, force):
    """As :func:`_oscillator_shoot`, with a compiled plugin force(t, q, qdot, None) ->
    (F,) (N) added at every stage. The rig calls the plugin with its clock; the truth with
    the time within the period (a plugin must not depend on time for the two to agree).
    Not cached: a compiled function is an argument."""
    m = Y0.shape[0]
    out = np.empty_like(Y0)
    y = np.empty(3)
    tmp = np.empty(3)
    ks = np.empty((4, 3))
    q = np.empty(1)
    qd = np.empty(1)
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
            for st in range(4):
                c = 0.0 if st == 0 else (dt if st == 3 else 0.5 * dt)
                for i in range(3):
                    tmp[i] = y[i] if st == 0 else y[i] + c * ks[st - 1, i]
                q[0] = tmp[0]
                qd[0] = tmp[1]
                f = force(t + c, q.copy(), qd.copy(), None)
                oscillator_deriv(tmp, ks[st], phi * np.cos(omega * (t + c)), f[0], K, E, mass)
            for i in range(3):
                y[i] += dt / 6.0 * (ks[0, i] + 2.0 * ks[1, i] + 2.0 * ks[2, i] + ks[3, i])
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
                 n_steps: int, su: np.ndarray, plugin=None):
        self.p = params
        self.plugin = plugin
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
        Y0, Phis = np.ascontiguousarray(U[:, :3]), np.ascontiguousarray(U[:, 3])
        if self.plugin is None:
            Y1 = _oscillator_shoot(Y0, Phis, self.omega, self.K, self.E, self.p.mass, self.n, H)
        else:
            Y1 = _oscillator_shoot_plugin(Y0, Phis, self.omega, self.K, self.E, self.p.mass,
                                          self.n, H, self.plugin)
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


