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
from scipy.optimize import lsq_linear

from .._fourier import K, amplitude, evaluate
from ..models.library import band_limited, columns, effect, states_of
from ..models.mechanistic import Drive, model_class
from ..models.refined import refined
from ..models.ude import UDE


def derivative_coeffs(c: np.ndarray, omega: float) -> np.ndarray:
    """Coefficients (15, ...) of d/dt of the series with phase omega t."""
    k = np.arange(1, K + 1).reshape((K,) + (1,) * (c.ndim - 1))
    d = np.zeros_like(c)
    d[1:K + 1] = omega * k * c[K + 1:]
    d[K + 1:] = -omega * k * c[1:K + 1]
    return d


class ParameterErrors(eqx.Module):
    """How far each orbit's bifurcation parameter may sit from its measured value: the
    offset is ``sigma * u`` with ``u`` an unknown of the periodic stage, and costs
    ``cost * u**2`` there (:mod:`.parameter_errors`). sigma 0: the parameter is exact."""
    sigma: jax.Array     # (n_orbits,) the parameter's scatter, in its own unit
    cost: jax.Array      # (n_orbits,) what a one-sigma offset adds to the orbit's misfit

    def take(self, idx) -> "ParameterErrors":
        return ParameterErrors(self.sigma[idx], self.cost[idx])


class TrainingData(eqx.Module):
    """Every orbit sampled at ``n`` phases: states, accelerations and what drives it."""
    ys: jax.Array        # (n_orbits, n, n_state)
    qdd: jax.Array       # (n_orbits, n, n_dof)
    period: jax.Array    # (n_orbits,) s
    drive: Drive         # batched: param (n_orbits,), omega, fc (n_orbits, 15)
    label: jax.Array     # (n_orbits,) +1 stable, -1 unstable, 0 unknown
    y_scale: jax.Array   # (n_state,) RMS of each state over the data
    amp_max: float = eqx.field(static=True)
    # (n_orbits,) each orbit's weight in the periodic objective; None: all alike
    weight: jax.Array | None = None
    # (n_orbits, n_state) each state's weight in an orbit's misfit; None: all alike
    state_weight: jax.Array | None = None
    # how many leading orbits are measurements; the rest guide the fit (None: all measured)
    measured: int | None = eqx.field(static=True, default=None)
    # errors in the measured parameters (None: exact)
    param_errors: ParameterErrors | None = None
    # (n_orbits,) each orbit's own stability margin (nan: the configured one; None: all
    # the configured one; ude_fit.analysis.margins)
    margin: jax.Array | None = None

    @property
    def n_orbits(self) -> int:
        return int(self.ys.shape[0])

    def measurements(self) -> "TrainingData":
        """The measured orbits alone: what the equation stage, the feature scaling and the
        regularity conditions are taken from (a guide orbit's accelerations and pitch are
        stand-ins, :mod:`.guides`)."""
        if self.measured is None:
            return self
        take = lambda x: x[:self.measured]
        errors = None if self.param_errors is None else self.param_errors.take(
            slice(0, self.measured))
        return TrainingData(take(self.ys), take(self.qdd), take(self.period),
                            jax.tree_util.tree_map(take, self.drive), take(self.label),
                            self.y_scale, self.amp_max, param_errors=errors,
                            margin=None if self.margin is None else take(self.margin))

    def only(self, active) -> "TrainingData":
        """The orbits where ``active`` (a boolean mask) at weight 1, every other at weight 0
        with the first active orbit standing in its place. The shapes stay, so the compiled
        loss serves every subset, and no orbit the model cannot yet follow is simulated (a
        weight of 0 does not stop a non-finite orbit from making the gradient non-finite)."""
        active = np.asarray(active, bool)
        if active.shape != (self.n_orbits,) or not active.any():
            raise ValueError("only: a mask over the orbits with at least one orbit in it")
        idx = np.where(active, np.arange(self.n_orbits), np.flatnonzero(active)[0])
        take = lambda x: x[idx]
        return TrainingData(take(self.ys), take(self.qdd), take(self.period),
                            jax.tree_util.tree_map(take, self.drive), take(self.label),
                            self.y_scale, self.amp_max, jnp.asarray(active, float),
                            None if self.state_weight is None else take(self.state_weight),
                            self.measured,
                            None if self.param_errors is None else self.param_errors.take(idx),
                            None if self.margin is None else take(self.margin))


def training_data(ds, n: int = 32) -> TrainingData:
    phi = 2 * np.pi * np.arange(n) / n
    ys, qdds, T, P, W, FC, L = [], [], [], [], [], [], []
    for o in ds.orbits:
        c = np.asarray(o.coeffs, float).T            # (15, n_coord)
        w = 2 * np.pi * o.frequency
        cd = derivative_coeffs(c, w)
        cdd = derivative_coeffs(cd, w)
        q, qd, qdd = (evaluate(x.T, phi).T for x in (c, cd, cdd))
        ys.append(np.concatenate([q, qd], axis=1))
        qdds.append(qdd)
        T.append(1.0 / o.frequency)
        P.append(o.parameter)
        W.append(w)
        FC.append(np.zeros(2 * K + 1) if o.forcing is None else np.asarray(o.forcing))
        L.append(0 if o.stable is None else (1 if o.stable else -1))
    ys = np.asarray(ys)
    amp = amplitude(np.asarray([o.coeffs[0] for o in ds.orbits]))
    y_scale = np.sqrt(np.mean(ys ** 2, axis=(0, 1)))
    return TrainingData(jnp.asarray(ys), jnp.asarray(np.asarray(qdds)), jnp.asarray(T),
                        Drive(jnp.asarray(P, float), jnp.asarray(W, float), jnp.asarray(FC)),
                        jnp.asarray(L, float), jnp.asarray(y_scale), float(amp.max()))


def _flat(data: TrainingData):
    n_o, n, ns = data.ys.shape
    nd = data.qdd.shape[-1]
    y = np.asarray(data.ys).reshape(-1, ns)
    qdd = np.asarray(data.qdd).reshape(-1, nd)
    rep = lambda a: np.repeat(np.asarray(a), n, axis=0)
    t = np.tile(np.asarray(data.period)[:, None] * np.arange(n) / n, 1).reshape(-1)
    return y, qdd, rep(data.drive.param), rep(data.drive.omega), rep(data.drive.fc), t


def _excitation(fc, omega, t):
    k = np.arange(1, K + 1)
    ph = (omega * t)[:, None] * k
    return fc[:, 0] + (fc[:, 1:K + 1] * np.cos(ph)).sum(1) + (fc[:, K + 1:] * np.sin(ph)).sum(1)


INPUT_GAIN = "input_gain"      # the free gain of an imposed input (identify's free_input)


def identify(data: TrainingData, system: str, base: dict | None = None,
             effects: tuple = (), *, fixed: dict | None = None, bootstrap: int = 0,
             seed: int = 0, free_input: bool = False):
    """Least-squares damping and stiffness (aerofoil) or all coefficients (oscillator),
    and the coefficients of any ``effects`` ((key, shape) pairs from the library), which
    make the result a :class:`~ude_fit._refined.Refined` model. ``base``: the known
    geometry (the design values where None); ``fixed``: fitted names whose values are
    given (e.g. by the user's parameter file), left out of the solve.

    The values no passive structure has at or below zero (the model class's
    ``must_be_positive``: damping and stiffness) are bounded below by zero (bounded least
    squares): a negative estimate, which noisy derivatives or a missing effect can give,
    becomes the closest physical one, and ``info["at_bound"]`` names it with its
    unconstrained estimate (``info["unconstrained"]``).

    Returns (mechanistic model, info) with the parameter standard errors (least squares,
    samples taken as independent) and, with ``bootstrap`` > 0, the standard deviations
    over that many refits to orbits resampled with replacement (the honest figure: the
    samples of one orbit are not independent).

    ``free_input``: the drive's input (the aerofoil's recorded control) enters with an
    unknown gain, identified with the rest as the value :data:`INPUT_GAIN`.
    """
    A, b, names, _ = regression(data, system, base, effects, free_input=free_input)
    fixed = {k: float(v) for k, v in (fixed or {}).items()}
    unknown = set(fixed) - set(names)
    if unknown:
        raise ValueError(f"identify: no fitted parameter {', '.join(sorted(unknown))}")
    # each equation weighted by its own force scale (before the given terms move over)
    w_eq = equation_weights(b)
    for k, v in fixed.items():
        b = b - A[:, :, names.index(k)] * v
    free = [j for j, n in enumerate(names) if n not in fixed]
    A, names = A[:, :, free], [names[j] for j in free]
    Aw, bw, col = _weighted(A, b, w_eq)
    lower = _lower_bounds(system, names)
    solve = lambda M, y: _bounded_solve(M, y, lower)
    theta = solve(Aw / col, bw) / col
    plain = np.linalg.lstsq(Aw / col, bw, rcond=None)[0] / col
    boot = None
    if bootstrap:
        n_o, n_eq = data.ys.shape[0], A.shape[1]
        rows = np.arange(A.shape[0] * n_eq).reshape(n_o, -1)     # orbit-major samples
        rng = np.random.default_rng(seed)
        draws = []
        for _ in range(bootstrap):
            idx = rows[rng.integers(0, n_o, n_o)].ravel()
            draws.append(solve((Aw / col)[idx], bw[idx]) / col)
        boot = np.asarray(draws).std(axis=0)
    res = bw - Aw @ theta
    dof = max(1, Aw.shape[0] - Aw.shape[1])
    s2 = float(res @ res) / dof
    cov = s2 * np.linalg.pinv((Aw / col).T @ (Aw / col)) / np.outer(col, col)
    at_bound = [n for n, v, lo in zip(names, theta, lower) if np.isfinite(lo) and v <= lo]
    values = {**fixed, **dict(zip(names, theta.tolist()))}
    mech = build(system, base, values, effects)
    info = {"parameters": values,
            "std_error": dict(zip(names, np.sqrt(np.clip(np.diag(cov), 0, None)).tolist())),
            "equation_rms": float(np.sqrt(np.mean(res ** 2))),
            "at_bound": at_bound,
            "unconstrained": {n: float(plain[names.index(n)]) for n in at_bound}}
    if boot is not None:
        info["bootstrap_std"] = dict(zip(names, boot.tolist()))
    return mech, info


def equation_weights(b: np.ndarray) -> np.ndarray:
    """Each equation's weight in the regression: one over its known force's RMS."""
    return 1.0 / np.sqrt(np.mean(b ** 2, axis=0) + 1e-300)


def _weighted(A, b, w_eq):
    """The regression's rows weighted (flattened) and its columns' RMS (1 where none)."""
    Aw = (A * w_eq[None, :, None]).reshape(-1, A.shape[-1])
    bw = (b * w_eq[None, :]).reshape(-1)
    col = np.sqrt(np.mean(Aw ** 2, axis=0))
    return Aw, bw, np.where(col > 0, col, 1.0)


def _lower_bounds(system: str, names) -> np.ndarray:
    positive = set(model_class(system).must_be_positive)
    return np.array([0.0 if n in positive else -np.inf for n in names])


def _bounded_solve(M, y, lower):
    if np.isfinite(lower).any():           # lower bounds unchanged by the column scaling
        return lsq_linear(M, y, bounds=(lower, np.inf), method="bvls").x
    return np.linalg.lstsq(M, y, rcond=None)[0]


def equation_residual(data: TrainingData, system: str, w_eq: np.ndarray,
                      base: dict | None = None) -> np.ndarray:
    """The weighted equation error left by :func:`identify`'s bounded solve on ``data``,
    with the equations' weights ``w_eq`` given (held fixed where the data are varied)."""
    A, b, names, _ = regression(data, system, base)
    Aw, bw, col = _weighted(A, b, w_eq)
    theta = _bounded_solve(Aw / col, bw, _lower_bounds(system, names)) / col
    return bw - Aw @ theta


def build(system: str, base: dict | None, values: dict, effects: tuple = ()):
    """The (refined) mechanistic model from identified ``values`` (names as identify's)."""
    mech = model_class(system).from_values(values, base)
    if not effects:
        return mech
    added = []
    for key, shape in effects:
        e = effect(system, key)
        added.append({"key": key, "shape": shape,
                      "coefficients": [values[f"{key}[{t}]"] for t in e.terms]})
    return refined(mech, added)


def regression(data: TrainingData, system: str, base: dict | None = None,
               effects: tuple = (), free_input: bool = False):
    """Equation-error regression ``A theta = b`` on every sample: A (N, n_eq, p), b (N, n_eq),
    the parameter names, and the unfitted mechanistic model. Effect columns enter with a
    minus sign: the model is ``known + A theta = 0`` with the effect on the right-hand side.
    ``free_input``: the drive's input acts on the first equation with an unknown gain (a
    last column, :data:`INPUT_GAIN`) instead of as a known force."""
    y, qdd, P, W, FC, t = _flat(data)
    cls = model_class(system)
    E = _excitation(FC, W, t)
    A, b, mech = cls.equation_error(y, qdd, P, np.zeros_like(E) if free_input else E, base)
    names = list(cls.fitted)
    # the model's own nonlinear columns (alpha^2, x^3, ...) compared in the band the
    # measured orbits carry, as the effect columns are (_library.band_limited)
    A = band_limited(A.reshape(A.shape[0], -1), data.ys.shape[1]).reshape(A.shape)
    if effects:
        S = states_of(data, system)
        extra = []
        for key, shape in effects:
            e = effect(system, key)
            X = columns(e, S, shape)
            block = np.zeros((X.shape[0], A.shape[1], X.shape[1]))
            block[:, e.equation, :] = -X
            extra.append(block)
            names += [f"{key}[{t}]" for t in e.terms]
        A = np.concatenate([A] + extra, axis=2)
    if free_input:
        col = np.zeros(A.shape[:2] + (1,))
        col[:, 0, 0] = -E
        A = np.concatenate([A, col], axis=2)
        names.append(INPUT_GAIN)
    return A, b, names, mech


def augment(data: TrainingData, mech) -> TrainingData:
    """``data`` with the hidden states of a refined model appended to every sample: each
    lag's steady periodic solution along the measured orbit (exact by Fourier series), so
    a model with hidden states can start, and be compared, on the data's orbits."""
    ys = np.asarray(data.ys)
    if not mech.n_hidden or ys.shape[2] == 2 * mech.n_dof + mech.n_hidden:   # (already)
        return data
    Z = mech.hidden_states(states_of(data, mech.system)).reshape(ys.shape[0], ys.shape[1], -1)
    ys2 = np.concatenate([ys, Z], axis=2)
    y_scale = np.sqrt(np.mean(ys2 ** 2, axis=(0, 1)))
    y_scale = np.where(y_scale > 0, y_scale, 1.0)
    if data.measured is not None:
        raise ValueError("augment: the hidden states go in before any guide orbit")
    return TrainingData(jnp.asarray(ys2), data.qdd, data.period, data.drive, data.label,
                        jnp.asarray(y_scale), data.amp_max, data.weight,
                        param_errors=data.param_errors, margin=data.margin)


def residual_forces(model: UDE, data: TrainingData):
    """What the correction must supply on every sample: features Z and forces R."""
    n_o, n, ns = data.ys.shape
    t = data.period[:, None] * jnp.arange(n)[None, :] / n

    data = augment(data, model.mech)
    nd = model.mech.n_dof

    def one(y, qdd, tt, drive):
        q, qd = y[:nd], y[nd:2 * nd]
        F = model.mech.force(q, qd, drive, y[2 * nd:]) if model.n_hidden else \
            model.mech.force(q, qd, drive)
        return model.features(y, drive), model.mech.residual_force(qdd, F, tt, drive)

    f = jax.vmap(jax.vmap(one, in_axes=(0, 0, 0, None)), in_axes=(0, 0, 0, 0))
    Z, R = f(data.ys, data.qdd, t, data.drive)
    return np.asarray(Z).reshape(-1, Z.shape[-1]), np.asarray(R).reshape(-1, R.shape[-1])
