"""From a dataset of orbits to training arrays, and the mechanistic model's parameters.

Identification is by *equation error*: on the Fourier-averaged orbits the states,
rates and accelerations are known analytically, and both mechanistic models are
linear in their fitted parameters, so one weighted least-squares solve gives
them, with no simulation and no starting guess.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._flow import evaluate_series
from ._models import (FLUTTER_NOMINAL, K_HARMONICS, UDE, Drive, Duffing7, FlutterQS, duffing7,
                      flutter_qs)


def derivative_coeffs(c: np.ndarray, omega: float) -> np.ndarray:
    """Coefficients (15, ...) of d/dt of the series with phase omega t."""
    K = K_HARMONICS
    k = np.arange(1, K + 1).reshape((K,) + (1,) * (c.ndim - 1))
    d = np.zeros_like(c)
    d[1:K + 1] = omega * k * c[K + 1:]
    d[K + 1:] = -omega * k * c[1:K + 1]
    return d


class TrainingData(eqx.Module):
    """Every orbit sampled at ``n`` phases: states, accelerations and what drives it."""
    ys: jax.Array        # (n_orbits, n, n_state)
    qdd: jax.Array       # (n_orbits, n, n_dof)
    period: jax.Array    # (n_orbits,) s
    drive: Drive         # batched: param (n_orbits,), omega, fc (n_orbits, 15)
    label: jax.Array     # (n_orbits,) +1 stable, -1 unstable, 0 unknown
    y_scale: jax.Array   # (n_state,) RMS of each state over the data
    amp_max: float = eqx.field(static=True)

    @property
    def n_orbits(self) -> int:
        return int(self.ys.shape[0])


def training_data(ds, n: int = 32) -> TrainingData:
    phi = 2 * np.pi * np.arange(n) / n
    ys, qdds, T, P, W, FC, L = [], [], [], [], [], [], []
    for o in ds.orbits:
        c = np.asarray(o.coeffs, float).T            # (15, n_coord)
        w = 2 * np.pi * o.frequency
        cd = derivative_coeffs(c, w)
        cdd = derivative_coeffs(cd, w)
        q, qd, qdd = (evaluate_series(x, phi) for x in (c, cd, cdd))
        ys.append(np.concatenate([q, qd], axis=1))
        qdds.append(qdd)
        T.append(1.0 / o.frequency)
        P.append(o.parameter)
        W.append(w)
        FC.append(np.zeros(2 * K_HARMONICS + 1) if o.forcing is None else np.asarray(o.forcing))
        L.append(0 if o.stable is None else (1 if o.stable else -1))
    ys = np.asarray(ys)
    amp = np.hypot(np.asarray([o.coeffs[0][1] for o in ds.orbits]),
                   np.asarray([o.coeffs[0][K_HARMONICS + 1] for o in ds.orbits]))
    y_scale = np.sqrt(np.mean(ys ** 2, axis=(0, 1)))
    return TrainingData(jnp.asarray(ys), jnp.asarray(np.asarray(qdds)), jnp.asarray(T),
                        Drive(jnp.asarray(P, float), jnp.asarray(W, float), jnp.asarray(FC)),
                        jnp.asarray(L, float), jnp.asarray(y_scale), float(amp.max()))


def _flat(data: TrainingData):
    n_o, n, ns = data.ys.shape
    nd = ns // 2
    y = np.asarray(data.ys).reshape(-1, ns)
    qdd = np.asarray(data.qdd).reshape(-1, nd)
    rep = lambda a: np.repeat(np.asarray(a), n, axis=0)
    t = np.tile(np.asarray(data.period)[:, None] * np.arange(n) / n, 1).reshape(-1)
    return y, qdd, rep(data.drive.param), rep(data.drive.omega), rep(data.drive.fc), t


def _excitation(fc, omega, t):
    K = K_HARMONICS
    k = np.arange(1, K + 1)
    ph = (omega * t)[:, None] * k
    return fc[:, 0] + (fc[:, 1:K + 1] * np.cos(ph)).sum(1) + (fc[:, K + 1:] * np.sin(ph)).sum(1)


def identify(data: TrainingData, system: str, base: dict | None = None):
    """Least-squares damping and stiffness (aerofoil) or all coefficients (oscillator).

    Returns (mechanistic model, info) with the parameter standard errors.
    """
    y, qdd, P, W, FC, t = _flat(data)
    if system == "flutter":
        base = dict(FLUTTER_NOMINAL if base is None else base)
        mech = flutter_qs(**base)
        nd = 2
        rows, rhs = [], []
        for V in np.unique(P):
            m = P == V
            A, known = mech.regressors(jnp.asarray(y[m, :nd]), jnp.asarray(y[m, nd:]),
                                       jnp.asarray(qdd[m]), V)
            rows.append(np.asarray(A))
            rhs.append(-np.asarray(known))
        A = np.concatenate(rows)          # (N, 2, p)
        b = np.concatenate(rhs)           # (N, 2)
        names = FlutterQS.fitted
    else:
        mech = duffing7()
        exc = _excitation(FC, W, t)
        A, known = mech.regressors(jnp.asarray(y[:, :1]), jnp.asarray(y[:, 1:]),
                                   jnp.asarray(qdd), jnp.asarray(exc))
        A, b = np.asarray(A), -np.asarray(known)
        names = Duffing7.fitted
    # each equation weighted by its own force scale, each column by its own size
    w_eq = 1.0 / np.sqrt(np.mean(b ** 2, axis=0) + 1e-300)
    Aw = (A * w_eq[None, :, None]).reshape(-1, A.shape[-1])
    bw = (b * w_eq[None, :]).reshape(-1)
    col = np.sqrt(np.mean(Aw ** 2, axis=0))
    col = np.where(col > 0, col, 1.0)
    theta_s, *_ = np.linalg.lstsq(Aw / col, bw, rcond=None)
    theta = theta_s / col
    res = bw - Aw @ theta
    dof = max(1, Aw.shape[0] - Aw.shape[1])
    s2 = float(res @ res) / dof
    cov = s2 * np.linalg.pinv((Aw / col).T @ (Aw / col)) / np.outer(col, col)
    values = dict(zip(names, theta.tolist()))
    if system == "flutter":
        mech = flutter_qs(**{**base, **values})
    else:
        mech = duffing7(**values)
    info = {"parameters": values,
            "std_error": dict(zip(names, np.sqrt(np.clip(np.diag(cov), 0, None)).tolist())),
            "equation_rms": float(np.sqrt(np.mean(res ** 2)))}
    return mech, info


def residual_forces(model: UDE, data: TrainingData):
    """What the correction must supply on every sample: features Z and forces R."""
    n_o, n, ns = data.ys.shape
    t = data.period[:, None] * jnp.arange(n)[None, :] / n

    def one(y, qdd, tt, drive):
        nd = ns // 2
        q, qd = y[:nd], y[nd:]
        if model.system == "oscillator":
            F = model.mech.force(q, qd, drive) + model.mech.g * drive.excitation(tt)
            r = qdd - F
        else:
            r = model.mech.mass(drive.param) @ qdd - model.mech.force(q, qd, drive)
        return model.features(y, drive), r

    f = jax.vmap(jax.vmap(one, in_axes=(0, 0, 0, None)), in_axes=(0, 0, 0, 0))
    Z, R = f(data.ys, data.qdd, t, data.drive)
    return np.asarray(Z).reshape(-1, Z.shape[-1]), np.asarray(R).reshape(-1, R.shape[-1])
