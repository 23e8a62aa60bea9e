"""Training the correction of a UDE: pure loss functions and the optimiser loop.

Three losses, used in this order by :func:`train_ude`:

* ``equation``: the correction against the residual force the mechanistic model
  leaves on every sample of the averaged orbits (no simulation; a fast start).
* ``trajectory`` (the paper's): integrate the UDE over one period from each
  measured initial state (diffrax, classical RK4 steps, checkpointed reverse mode)
  and compare the states at the measured phases.
* ``periodic`` (beyond the paper): every orbit gets its own initial state and,
  for the autonomous aerofoil, its own period as unknowns; the loss asks for a
  *closed* model orbit that matches the measured one, with the stability the
  data says it has. Stability enters through the sign of the characteristic
  polynomial of the monodromy matrix at 1 (for the aerofoil with its trivial
  multiplier factored out), which changes sign exactly when a real multiplier
  crosses 1, as it does at a fold: smooth and with no eigen-decomposition.

Optimisation: Adam, then L-BFGS (optax), all float64. Losses are module-level
functions of (trainable, static, data), compiled once per problem structure and
shared by every random start.
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax

from ._flow import diffrax_samples, rk4_orbit
from ._identify import TrainingData, residual_forces
from ._models import UDE, MLPCorrection, PolynomialParamCorrection, feature_scaling
from ._penalties import Penalty, penalty_sum, regularity_points


class Diverged(RuntimeError):
    """Training produced a non-finite loss; the start is dropped."""


@dataclass(frozen=True)
class TrainConfig:
    """How one correction is trained: the network, the optimiser's steps, the shooting
    losses' weights and the penalties (:mod:`._penalties`). A field left at None takes its
    system's default (:data:`SYSTEM_DEFAULTS`, applied by :meth:`for_system`). Checks its
    own fields when built (ValueError naming the field)."""
    width: int = 12
    depth: int = 2
    equation_steps: int | None = None         # Adam steps on the equation loss
    equation_lbfgs_steps: int | None = None   # L-BFGS steps on the equation loss
    adam_steps: int | None = None             # Adam steps on the trajectory/periodic loss
    lbfgs_steps: int | None = None            # L-BFGS steps on the trajectory/periodic loss
    learning_rate: float = 3e-3
    substeps: int | None = None  # RK4 steps between two samples of the orbit
    closure_weight: float = 10.0
    stability_weight: float = 10.0
    stability_margin: float = 0.02
    init_scale: float = 1e-2
    param_scale: float = 1.0     # the parameter input is standardised by this times its spread
    # how the NN correction depends on the parameter: "input" (a network input like the
    # states) or "polynomial" (a polynomial of param_degree in it, state-dependent
    # coefficients; PolynomialParamCorrection)
    param_dependence: str = "input"
    param_degree: int = 2
    penalties: tuple[Penalty, ...] = ()

    def __post_init__(self):
        for name in ("width", "depth", "param_degree"):
            _check_int(name, getattr(self, name), 1)
        for name in ("equation_steps", "equation_lbfgs_steps", "adam_steps", "lbfgs_steps"):
            if getattr(self, name) is not None:
                _check_int(name, getattr(self, name), 0)
        if self.substeps is not None:
            _check_int("substeps", self.substeps, 1)
        for name in ("learning_rate", "init_scale", "param_scale"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be a positive number, not {v!r}")
        for name in ("closure_weight", "stability_weight", "stability_margin"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ValueError(f"{name} must be a number at least 0, not {v!r}")
        if self.param_dependence not in PARAM_DEPENDENCE:
            raise ValueError(f"param_dependence must be input or polynomial, not "
                             f"{self.param_dependence!r}")
        object.__setattr__(self, "penalties", tuple(self.penalties))
        kinds = [type(p) for p in self.penalties]
        for p in self.penalties:
            if not isinstance(p, Penalty):
                raise ValueError(f"penalties must be Penalty objects, not {p!r}")
        if len(set(kinds)) != len(kinds):
            raise ValueError("penalties: each kind at most once")

    def for_system(self, system: str) -> "TrainConfig":
        """This configuration with every None field set to ``system``'s default."""
        if system not in SYSTEM_DEFAULTS:
            raise ValueError(f"unknown system {system!r} (flutter or oscillator)")
        cfg = dataclasses.replace(self, **{k: v for k, v in SYSTEM_DEFAULTS[system].items()
                                           if getattr(self, k) is None})
        if cfg.equation_lbfgs_steps is None:
            cfg = dataclasses.replace(cfg, equation_lbfgs_steps=cfg.lbfgs_steps)
        return cfg

    def penalty(self, kind: type) -> Penalty | None:
        """The penalty of class ``kind``, if any."""
        return next((p for p in self.penalties if isinstance(p, kind)), None)

    def needs_points(self) -> bool:
        """Whether any active penalty reads the regularity points."""
        return any(p.needs_points and p.weight for p in self.penalties)

    def to_json(self) -> dict:
        d = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)
             if f.name != "penalties"}
        d["penalties"] = {k: v for p in self.penalties for k, v in p.to_json().items()}
        return d


def _check_int(name: str, v, least: int) -> None:
    if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < least:
        raise ValueError(f"{name} must be an integer at least {least}, not {v!r}")


PARAM_DEPENDENCE = ("input", "polynomial")

# Per-system defaults. The forced oscillator's orbits are smooth enough at 64 RK4 steps per
# period (2 per sample; amplitude within 1e-5 of the converged orbit up to 10 mm), which
# makes its shooting losses 3x cheaper; its correction is cheap to fit to the equation
# residual, and that first stage decides most of the final quality, so it gets more steps.
SYSTEM_DEFAULTS = {
    "flutter": dict(equation_steps=1500, adam_steps=300, lbfgs_steps=100, substeps=4),
    "oscillator": dict(equation_steps=4000, equation_lbfgs_steps=1000, adam_steps=300,
                       lbfgs_steps=100, substeps=2),
}


def _trainable_spec(correction):
    spec = jax.tree_util.tree_map(lambda _: False, correction)
    return eqx.tree_at(lambda c: c.mlp, spec,
                       replace=jax.tree_util.tree_map(eqx.is_inexact_array, correction.mlp))


def new_correction(model: UDE, data: TrainingData, key, cfg: TrainConfig):
    Z, R = residual_forces(model, data)
    sc = feature_scaling(Z, R)
    if cfg.param_scale != 1.0:
        sc = eqx.tree_at(lambda s: s.z_scale, sc, sc.z_scale.at[-1].multiply(cfg.param_scale))
    if cfg.param_dependence == "polynomial":
        return PolynomialParamCorrection(Z.shape[1], R.shape[1], sc, degree=cfg.param_degree,
                                         width=cfg.width, depth=cfg.depth, key=key,
                                         init_scale=cfg.init_scale)
    return MLPCorrection(Z.shape[1], R.shape[1], sc, width=cfg.width,
                         depth=cfg.depth, key=key, init_scale=cfg.init_scale)


# ---------------------------------------------------------------------------------------
# losses
# ---------------------------------------------------------------------------------------

def equation_loss(params, static, mech, Z, R, penalties=(), reg=None):
    """The correction against the residual forces R at the features Z, plus the penalties
    that act in the equation stage."""
    corr = eqx.combine(params["corr"], static)
    pred = jax.vmap(corr)(Z)
    loss = jnp.mean(((pred - R) / corr.scaling.out_scale) ** 2)
    return loss + penalty_sum(penalties, "equation", UDE(mech, corr), reg)


def _simulate_with_monodromy(model, y0, T, drive, n, sub):
    """One pass of forward-mode autodiff: end state, samples and the monodromy matrix
    (the tangent integration rides along with the primal one, so the orbit is
    integrated once)."""
    def flow(y):
        yT, ys = rk4_orbit(model, y, T, drive, n * sub)
        return yT, (yT, ys)
    M, (yT, ys) = jax.jacfwd(flow, has_aux=True)(y0)
    return yT, ys[::sub], M


def _stability_indicator(system: str, M):
    """Positive for a stable orbit, negative once a real multiplier passes 1."""
    A = jnp.eye(M.shape[0]) - M
    if system == "flutter":
        # d/dlambda det(lambda I - M) at 1 = sum of the principal (n-1)-minors of I - M;
        # it equals prod over the non-trivial multipliers of (1 - mu).
        k = A.shape[0]
        minors = [jnp.linalg.det(jnp.delete(jnp.delete(A, i, 0), i, 1)) for i in range(k)]
        return sum(minors)
    return jnp.linalg.det(A)


def trajectory_loss(params, static, mech, data: TrainingData, sub: int, penalties=(),
                    reg=None):
    """One-period trajectories from the measured states against the measured orbits (the
    paper's loss), plus the penalties that act in the trajectory stage."""
    model = UDE(mech, eqx.combine(params["corr"], static))
    return (_trajectory_error(model, data, sub)
            + penalty_sum(penalties, "trajectory", model, reg))


def _trajectory_error(model, data: TrainingData, sub: int):
    n = data.ys.shape[1]

    def one(ys, T, drive):
        sim = diffrax_samples(model, ys[0], T, drive, n, sub)
        return jnp.mean(((sim - ys) / data.y_scale) ** 2)

    return jnp.mean(jax.vmap(one)(data.ys, data.period, data.drive))


def _periodic_objective(model, params, data: TrainingData, cfg: TrainConfig):
    """Closed model orbits through the measured ones, with the measured stability."""
    w_close, w_stab, margin = cfg.closure_weight, cfg.stability_weight, cfg.stability_margin
    sub = cfg.substeps
    n = data.ys.shape[1]
    autonomous = model.system == "flutter"

    def one(ys, y0, T, drive, label):
        yT, sim, M = _simulate_with_monodromy(model, y0, T, drive, n, sub)
        s = _stability_indicator(model.system, M)
        fit = jnp.mean(((sim - ys) / data.y_scale) ** 2)
        close = jnp.sum(((yT - y0) / data.y_scale) ** 2)
        stab = jnp.where(label == 0, 0.0, jax.nn.relu(margin - label * s) ** 2)
        return fit + w_close * close + w_stab * stab

    y0 = data.ys[:, 0, :] + params["dy0"] * data.y_scale
    T = data.period * (1.0 + params["dT"]) if autonomous else data.period
    return jnp.mean(jax.vmap(one)(data.ys, y0, T, data.drive, data.label))


def periodic_loss(params, static, mech, data: TrainingData, cfg: TrainConfig, reg=None):
    """Closed model orbits through the measured ones with the measured stability, plus the
    penalties that act in the periodic stage."""
    model = UDE(mech, eqx.combine(params["corr"], static))
    return (_periodic_objective(model, params, data, cfg)
            + penalty_sum(cfg.penalties, "periodic", model, reg))


def _mech_leaves(mech):
    """The fitted parameters of a mechanistic model as a tuple of arrays: the base
    model's fitted fields, then each added effect's coefficient vector."""
    base = getattr(mech, "base", mech)
    out = tuple(getattr(base, f) for f in base.fitted)
    if base is not mech:
        out = out + tuple(a.coefficients for a in mech.added)
    return out


def _mech_with(mech, sizes, base, scale, delta):
    flat = base + scale * delta
    vals, i = [], 0
    for shp in sizes:
        k = int(np.prod(shp)) if shp else 1
        vals.append(flat[i:i + k].reshape(shp))
        i += k
    return eqx.tree_at(_mech_leaves, mech, tuple(vals))


def _mech_periodic_loss(params, mech, sizes, base, scale, data, cfg):
    model = UDE(_mech_with(mech, sizes, base, scale, params["delta"]))
    return _periodic_objective(model, params, data, cfg)


def refine_mechanistic(model: UDE, data: TrainingData, *, cfg: TrainConfig, progress=None):
    """Output-error identification of the mechanistic parameters: the equation-error
    estimate (or any start) refined so that the model has closed orbits through the
    measured ones with the measured stability. Returns (UDE without correction, info).
    ``data`` must carry the model's hidden states, if it has any (``augment``)."""
    cfg = cfg.for_system(model.system)
    mech = model.mech
    leaves = _mech_leaves(mech)
    sizes = tuple(tuple(jnp.shape(x)) for x in leaves)
    base = jnp.concatenate([jnp.ravel(jnp.asarray(x, float)) for x in leaves])
    scale = jnp.where(jnp.abs(base) > 0, jnp.abs(base), 1.0)
    params = {"delta": jnp.zeros(base.size), "dy0": jnp.zeros(data.ys[:, 0, :].shape)}
    if model.system == "flutter":
        params["dT"] = jnp.zeros(data.period.shape)
    params, v = minimize(_mech_periodic_loss, params,
                         (mech, sizes, base, scale, data, cfg),
                         adam_steps=cfg.adam_steps, lbfgs_steps=cfg.lbfgs_steps,
                         lr=cfg.learning_rate, progress=progress, stage="mechanistic")
    refined = _mech_with(mech, sizes, base, scale, params["delta"])
    return UDE(refined), {"loss": v}


# ---------------------------------------------------------------------------------------
# optimiser loop
# ---------------------------------------------------------------------------------------

_ADAM_CHUNK = 25
_OPTIMISERS: dict = {}


def _adam(lr):
    if ("adam", lr) not in _OPTIMISERS:
        _OPTIMISERS[("adam", lr)] = optax.adam(lr)
    return _OPTIMISERS[("adam", lr)]


def _lbfgs():
    if "lbfgs" not in _OPTIMISERS:
        _OPTIMISERS["lbfgs"] = optax.lbfgs()
    return _OPTIMISERS["lbfgs"]


@eqx.filter_jit
def _adam_chunk(params, state, loss, args, opt):
    def body(carry, _):
        p, s = carry
        val, g = jax.value_and_grad(loss)(p, *args)
        u, s = opt.update(g, s, p)
        return (optax.apply_updates(p, u), s), val
    (params, state), vals = jax.lax.scan(body, (params, state), None, length=_ADAM_CHUNK)
    return params, state, vals[-1]


def _strong_types(tree):
    """The same values without JAX's weak types: optax.lbfgs's fresh state holds weakly
    typed scalars that its first update returns strongly typed, so without this the step
    is compiled twice (several seconds for a shooting loss)."""
    return jax.tree_util.tree_map(
        lambda x: jnp.array(x, dtype=x.dtype) if isinstance(x, jax.Array) else x, tree)


@eqx.filter_jit
def _lbfgs_step(params, state, loss, args, opt):
    f = lambda p: loss(p, *args)
    vg = optax.value_and_grad_from_state(f)
    val, g = vg(params, state=state)
    u, state = opt.update(g, state, params, value=val, grad=g, value_fn=f)
    return optax.apply_updates(params, u), state, val


def minimize(loss, params, args, *, adam_steps: int, lbfgs_steps: int, lr: float,
             progress=None, stage: str = ""):
    """Adam then L-BFGS on ``loss(params, *args)``; raises :class:`Diverged` on NaN."""
    t0 = time.perf_counter()
    val = float("nan")
    if adam_steps > 0:
        opt = _adam(lr)
        state = opt.init(params)
        for done in range(_ADAM_CHUNK, adam_steps + _ADAM_CHUNK, _ADAM_CHUNK):
            params, state, v = _adam_chunk(params, state, loss, args, opt)
            val = float(v)
            if not np.isfinite(val):
                raise Diverged(f"{stage}: loss is not finite at Adam step {done}")
            if progress:
                progress(stage=stage, optimiser="adam", step=min(done, adam_steps),
                         steps=adam_steps, loss=val, elapsed=time.perf_counter() - t0)
    if lbfgs_steps > 0:
        opt = _lbfgs()
        state = _strong_types(opt.init(params))
        best = (np.inf, params)
        for k in range(1, lbfgs_steps + 1):
            params, state, v = _lbfgs_step(params, state, loss, args, opt)
            val = float(v)
            if not np.isfinite(val):
                if np.isfinite(best[0]):
                    params, val = best[1], best[0]
                    break
                raise Diverged(f"{stage}: loss is not finite at L-BFGS step {k}")
            if val < best[0]:
                best = (val, params)
            if progress and (k % 10 == 0 or k == lbfgs_steps):
                progress(stage=stage, optimiser="lbfgs", step=k, steps=lbfgs_steps, loss=val,
                         elapsed=time.perf_counter() - t0)
    return params, val


def train_ude(model: UDE, data: TrainingData, *, key, cfg: TrainConfig, training: str,
              progress=None) -> tuple[UDE, dict]:
    """Fit a fresh MLP correction on top of ``model.mech``; returns (UDE, info)."""
    cfg = cfg.for_system(model.system)
    corr = new_correction(model, data, key, cfg)
    trainable, static = eqx.partition(corr, _trainable_spec(corr))
    mech = model.mech
    info = {"training": training}
    Z, R = residual_forces(UDE(mech), data)
    params = {"corr": trainable}
    reg = regularity_points(data) if cfg.needs_points() else None
    params, v = minimize(equation_loss, params,
                         (static, mech, jnp.asarray(Z), jnp.asarray(R), cfg.penalties, reg),
                         adam_steps=cfg.equation_steps, lbfgs_steps=cfg.equation_lbfgs_steps,
                         lr=1e-2, progress=progress, stage="equation")
    info["equation_loss"] = v
    if training == "trajectory":
        params, v = minimize(trajectory_loss, params,
                             (static, mech, data, cfg.substeps, cfg.penalties, reg),
                             adam_steps=cfg.adam_steps, lbfgs_steps=cfg.lbfgs_steps,
                             lr=cfg.learning_rate, progress=progress, stage="trajectory")
    elif training == "periodic":
        # initial states and periods as scaled offsets from the measured ones, so one
        # Adam step size suits metres, radians and seconds alike
        params = {"corr": params["corr"], "dy0": jnp.zeros(data.ys[:, 0, :].shape)}
        if model.system == "flutter":
            params["dT"] = jnp.zeros(data.period.shape)
        params, v = minimize(periodic_loss, params, (static, mech, data, cfg, reg),
                             adam_steps=cfg.adam_steps, lbfgs_steps=cfg.lbfgs_steps,
                             lr=cfg.learning_rate, progress=progress, stage="periodic")
    elif training != "equation":
        raise ValueError(f"unknown training mode {training!r} (trajectory, periodic, equation)")
    info["final_loss"] = v
    return UDE(mech, eqx.combine(params["corr"], static)), info
