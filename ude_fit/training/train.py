"""Training the correction of a UDE: the stages and the optimiser loop.

The stages, in the order :func:`train_ude` runs them (losses in :mod:`.losses`):

* ``equation``: the correction against the residual force the mechanistic model
  leaves on every sample of the averaged orbits (no simulation; a fast start).
* ``trajectory`` (the paper's): integrate the UDE over one period from each
  measured initial state and compare the states at the measured phases.
* ``periodic`` (beyond the paper): closed model orbits through the measured ones, with
  the stability the data says they have; with ``amplitude_stages`` (aerofoil,
  experimental) first on the smallest orbit, then one orbit more per stage in order of
  amplitude (:func:`.branch.amplitude_stages`). With ``collocation`` its first, long
  training runs on the same objective with every orbit collocated (:mod:`.collocation`,
  a sixth of shooting's cost per step), and the periodic stage's own steps finish it by
  shooting.
* ``constraints`` (aerofoil, ``constraint_rounds`` > 0): where the periodic fit breaks
  the energy-rising or rest-stability condition, training goes on with the broken penalty
  weighted from the data's misfit (:func:`.rounds.enforce_constraints`); a fit that meets
  both is not touched.
* ``branch`` (aerofoil, ``branch_rounds`` > 0, experimental): the measured orbits asked to
  lie on the branch from the Hopf point (:func:`.rounds.follow_branch`).
* ``monotone`` (aerofoil, ``monotone_rounds`` > 0, experimental): the branch monotone
  between orbits of one stability and rising above the largest stable one
  (:func:`.rounds.keep_monotone`).

:func:`train_on` trains a trained UDE on, from its weights, on data that may hold orbits
its first training did not (the guide rounds, :mod:`ude_fit.guide_rounds`).

Optimisation: Adam, then L-BFGS (optax), all float64. :func:`train_ensemble` trains many
random starts at once, vmapped (:mod:`.optimise`). :func:`refine_mechanistic` is the
mechanistic model's output-error identification on the same periodic objective.
"""
from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._precision import require_float64
from ..models.amplitude import RestLinear, SizeBasis, amplitude_correction, resolve
from ..models.corrections import (MLPCorrection, PolynomialParamCorrection,
                                  RestFreeCorrection, Scaling, feature_scaling)
from ..models.ude import UDE
from .amplitude_start import start_amplitude
from .collocation import (collocation_loss, collocation_unknowns, plan_legs,
                          shooting_unknowns)
from .branch import amplitude_stages
from .identify import TrainingData, residual_forces
from .losses import (constrained_periodic_loss, equation_loss, orbit_unknowns, periodic_loss,
                     periodic_objective, trajectory_loss)
from .optimise import Diverged, descend, lane_of, minimize
from .options import TrainConfig
from .penalties import constraints_for, regularity_points
from .rounds import enforce_constraints, follow_branch, keep_monotone


def _trainable_spec(correction):
    """Every array of the correction is trained but its fixed parts (input/output scaling,
    an amplitude form's knots)."""
    fixed = (Scaling, SizeBasis, RestLinear)
    return jax.tree_util.tree_map(
        lambda x: False if isinstance(x, fixed) else eqx.is_inexact_array(x), correction,
        is_leaf=lambda x: isinstance(x, fixed))


def new_correction(model: UDE, data: TrainingData, key, cfg: TrainConfig):
    Z, R = residual_forces(model, data)
    sc = feature_scaling(Z, R)
    if cfg.param_scale != 1.0:
        sc = eqx.tree_at(lambda s: s.z_scale, sc, sc.z_scale.at[-1].multiply(cfg.param_scale))
    if cfg.form == "amplitude":
        corr = amplitude_correction(Z, model.mech.n_dof, sc, key=key,
                                    init_scale=cfg.init_scale)
        return start_amplitude(UDE(model.mech, corr), data).correction
    if cfg.param_dependence == "polynomial":
        inner = PolynomialParamCorrection(Z.shape[1], R.shape[1], sc, degree=cfg.param_degree,
                                          width=cfg.width, depth=cfg.depth, key=key,
                                          init_scale=cfg.init_scale)
    else:
        inner = MLPCorrection(Z.shape[1], R.shape[1], sc, width=cfg.width,
                              depth=cfg.depth, key=key, init_scale=cfg.init_scale)
    return RestFreeCorrection(inner, model.mech.n_dof) if cfg.rest_free else inner


def _mech_leaves(mech):
    """The fitted parameters of a mechanistic model as a tuple of arrays: the base
    model's fitted fields, then each added effect's coefficient vector."""
    base = mech.base
    return (tuple(getattr(base, f) for f in base.fitted)
            + tuple(a.coefficients for a in mech.effects))


# the smallest positive value a sign-bounded parameter can take in the periodic refinement,
# in units of its scale (|start value|, or 1 where it starts at its bound 0)
_POSITIVE_FLOOR = 1e-3


def _positive_part(u):
    """A smooth map of the real line onto the positive numbers, u for u >> floor."""
    return 0.5 * (u + jnp.sqrt(u * u + _POSITIVE_FLOOR ** 2))


def _positive_mask(mech, sizes) -> np.ndarray:
    """True for the entries of the flat parameter vector no passive structure has at or
    below zero (the model class's ``must_be_positive``), as the equation-error
    identification bounds them."""
    names = tuple(mech.base.fitted) + ("",) * len(mech.effects)
    positive = set(mech.must_be_positive)
    return np.concatenate([np.full(int(np.prod(shp)) if shp else 1, n in positive)
                           for n, shp in zip(names, sizes)])


def _mech_with(mech, sizes, base, scale, delta, positive):
    """The model at ``delta``: free entries move as base + scale·delta; sign-bounded ones
    as scale·p(u₀ + delta), with p :func:`_positive_part` and u₀ its start."""
    v0 = jnp.maximum(base / scale, _POSITIVE_FLOOR)
    u0 = v0 - _POSITIVE_FLOOR ** 2 / (4.0 * v0)          # p(u0) = v0
    flat = jnp.where(positive, scale * _positive_part(u0 + delta), base + scale * delta)
    vals, i = [], 0
    for shp in sizes:
        k = int(np.prod(shp)) if shp else 1
        vals.append(flat[i:i + k].reshape(shp))
        i += k
    return eqx.tree_at(_mech_leaves, mech, tuple(vals))


def _mech_periodic_loss(params, mech, sizes, base, scale, positive, data, cfg):
    model = UDE(_mech_with(mech, sizes, base, scale, params["delta"], positive))
    return periodic_objective(model, params, data, cfg)


def refine_mechanistic(model: UDE, data: TrainingData, *, cfg: TrainConfig, progress=None):
    """Output-error identification of the mechanistic parameters: the equation-error
    estimate (or any start) refined so that the model has closed orbits through the
    measured ones with the measured stability. The damping and stiffness values the
    equation error bounds at zero stay positive here too (:func:`_mech_with`).
    Returns (UDE without correction, info). ``data`` must carry the model's hidden
    states, if it has any (``augment``)."""
    cfg = cfg.for_system(model.system)
    mech = model.mech
    leaves = _mech_leaves(mech)
    sizes = tuple(tuple(jnp.shape(x)) for x in leaves)
    base = jnp.concatenate([jnp.ravel(jnp.asarray(x, float)) for x in leaves])
    scale = jnp.where(jnp.abs(base) > 0, jnp.abs(base), 1.0)
    positive = jnp.asarray(_positive_mask(mech, sizes))
    params = {"delta": jnp.zeros(base.size), **orbit_unknowns(data, model.mech.autonomous)}
    params, v = minimize(_mech_periodic_loss, params,
                         (mech, sizes, base, scale, positive, data, cfg),
                         adam_steps=cfg.adam_steps, lbfgs_steps=cfg.lbfgs_steps,
                         lr=cfg.learning_rate, progress=progress, stage="mechanistic")
    refined = _mech_with(mech, sizes, base, scale, params["delta"], positive)
    return UDE(refined), {"loss": v}


def _shooting_start(cparams, static, mech, data, cfg, lanes):
    """Shooting's unknowns where collocation left each start (lane by lane in an
    ensemble: solved series are solved for each start's own model)."""
    def one(p):
        model = resolve(UDE(mech, eqx.combine(p["corr"], static)))
        return shooting_unknowns(model, p, data, cfg)
    if lanes is None:
        return one(cparams)
    return _stack([one(lane_of(cparams, i)) for i in range(lanes)])


def _stack(trees):
    return jax.tree_util.tree_map(lambda *xs: jnp.stack(xs), *trees)


def train_ude(model: UDE, data: TrainingData, *, key, cfg: TrainConfig, training: str,
              progress=None) -> tuple[UDE, dict]:
    """Fit a fresh MLP correction on top of ``model.mech``; returns (UDE, info); raises
    :class:`~.optimise.Diverged` if its loss goes non-finite."""
    (result,) = _train(model, data, [key], cfg, training, progress, ensemble=False)
    if isinstance(result, Diverged):
        raise result
    return result


def train_ensemble(model: UDE, data: TrainingData, *, keys, cfg: TrainConfig,
                   training: str, progress=None) -> list:
    """One fresh MLP correction per key, trained together as one vectorised ensemble
    (every stage's steps vmapped over the starts, optimiser state included): start k
    is what :func:`train_ude` gives with ``keys[k]``, to rounding (constraint rounds, which
    differ from start to start, are not run unless asked for, and then refused). Returns,
    per key, (UDE, info) or the :class:`~.optimise.Diverged` that dropped it."""
    if cfg.constraint_rounds is None:
        cfg = dataclasses.replace(cfg, constraint_rounds=0)
    return _train(model, data, list(keys), cfg, training, progress, ensemble=True)


def train_on(model: UDE, data: TrainingData, *, cfg: TrainConfig,
             constraint_weights: dict | None = None, progress=None,
             stage: str = "periodic, again") -> tuple[UDE, float]:
    """``model``'s correction trained on with the periodic loss of ``data``, from its
    weights: every orbit's initial state and period free again (as offsets from the
    measured ones), the constraint conditions at ``constraint_weights`` (by option name,
    as the rounds left them; a condition not named weighs 0). Returns (UDE, loss); raises
    :class:`~.optimise.Diverged` if the loss goes non-finite."""
    require_float64("train_on")
    cfg = cfg.for_system(model.system)
    corr, static = eqx.partition(model.correction, _trainable_spec(model.correction))
    params = {"corr": corr, **orbit_unknowns(data, model.mech.autonomous)}
    # only the conditions the rounds weighted (one at weight 0 would cost its evaluation)
    weighted = {k: w for k, w in (constraint_weights or {}).items() if w}
    constraints = tuple(c for c in constraints_for(cfg) if c.option in weighted)
    weights = jnp.asarray([weighted[c.option] for c in constraints])
    reg = (regularity_points(data.measurements())
           if constraints or cfg.needs_points() else None)
    params, loss, failed = descend(
        constrained_periodic_loss, params,
        (static, model.mech, data, cfg, reg, constraints, weights), lanes=None,
        adam_steps=cfg.adam_steps, lbfgs_steps=cfg.lbfgs_steps, lr=cfg.learning_rate,
        progress=progress, stage=stage)
    if failed:
        raise Diverged(failed[0])
    return (resolve(UDE(model.mech, eqx.combine(params["corr"], static))),
            float(np.asarray(loss).reshape(-1)[0]))


def _train(model: UDE, data: TrainingData, keys: list, cfg: TrainConfig, training: str,
           progress, ensemble: bool) -> list:
    require_float64("train_ude")
    if training not in ("trajectory", "periodic", "equation"):
        raise ValueError(f"unknown training mode {training!r} (trajectory, periodic, equation)")
    cfg = cfg.for_system(model.system)
    # the starts differ only in their network's weights; scaling and structure are shared
    measured = data.measurements()      # without the guide orbits, if any (.guides)
    parts = [eqx.partition(c, _trainable_spec(c))
             for c in (new_correction(model, measured, k, cfg) for k in keys)]
    static = parts[0][1]
    lanes = len(keys) if ensemble else None
    lead = (len(keys),) if ensemble else ()
    params = {"corr": _stack([p for p, _ in parts]) if ensemble else parts[0][0]}
    mech = model.mech
    reg = regularity_points(measured) if cfg.needs_points() else None
    # the first training's steps: from the mechanistic model it has the whole correction to
    # learn
    adam_steps, lbfgs_steps = ((cfg.start_adam_steps, cfg.start_lbfgs_steps)
                               if cfg.from_mechanistic else (cfg.adam_steps, cfg.lbfgs_steps))
    # the amplitude form starts from the orbits' energy balance instead of the residual
    # forces, and from_mechanistic from the mechanistic model: no equation stage, and no
    # residual forces to compute for it
    if cfg.form == "amplitude" or cfg.from_mechanistic:
        eq_loss, failed = np.full(len(keys), np.nan), {}
    else:
        Z, R = residual_forces(UDE(mech), measured)
        params, eq_loss, failed = descend(
            equation_loss, params, (static, mech, jnp.asarray(Z), jnp.asarray(R),
                                    cfg.penalties, reg),
            lanes=lanes, adam_steps=cfg.equation_steps, lbfgs_steps=cfg.equation_lbfgs_steps,
            lr=1e-2, progress=progress, stage="equation")
    loss = eq_loss
    if training == "trajectory":
        params, loss, failed = descend(
            trajectory_loss, params, (static, mech, data, cfg.substeps, cfg.penalties, reg),
            lanes=lanes, adam_steps=adam_steps, lbfgs_steps=lbfgs_steps,
            lr=cfg.learning_rate, failed=failed, progress=progress, stage="trajectory")
    elif training == "periodic":
        params = {"corr": params["corr"], **orbit_unknowns(data, model.mech.autonomous, lead)}
        # the orbits one at a time in order of amplitude first, as continuation from the
        # Hopf point meets them (half the steps each), then all of them
        for active in (amplitude_stages(data) if cfg.amplitude_stages else ()):
            params, loss, failed = descend(
                periodic_loss, params, (static, mech, data.only(active), cfg, reg),
                lanes=lanes, adam_steps=cfg.adam_steps // 2, lbfgs_steps=cfg.lbfgs_steps // 2,
                lr=cfg.learning_rate, failed=failed, progress=progress,
                stage=f"periodic, {int(active.sum())} smallest orbits")
        if cfg.collocation:
            # the long first training on the collocated orbits, leg by leg of its plan (the
            # period and parameter offsets carried from leg to leg); shooting finishes it
            # with the periodic stage's own steps, from the orbits collocation found
            offsets = {}
            for series, leg_adam, leg_lbfgs in plan_legs(cfg.collocation_series, adam_steps,
                                                         lbfgs_steps):
                leg_cfg = dataclasses.replace(cfg, collocation_series=series)
                cparams = {"corr": params["corr"],
                           **collocation_unknowns(data, model.mech.autonomous, lead, series),
                           **offsets}
                cparams, loss, failed = descend(
                    collocation_loss, cparams, (static, mech, data, leg_cfg, reg),
                    lanes=lanes, adam_steps=leg_adam, lbfgs_steps=leg_lbfgs,
                    lr=cfg.learning_rate, failed=failed, progress=progress,
                    stage=f"collocation, {series} series")
                params = {"corr": cparams["corr"]}
                offsets = {k: v for k, v in cparams.items() if k in ("dT", "dP")}
            params = {"corr": cparams["corr"],
                      **_shooting_start(cparams, static, mech, data, leg_cfg, lanes)}
            adam_steps, lbfgs_steps = cfg.adam_steps, cfg.lbfgs_steps
        params, loss, failed = descend(
            periodic_loss, params, (static, mech, data, cfg, reg), lanes=lanes,
            adam_steps=adam_steps, lbfgs_steps=lbfgs_steps, lr=cfg.learning_rate,
            failed=failed, progress=progress, stage="periodic")
    enforced = {}
    if training == "periodic" and cfg.constraint_rounds and not failed:
        if ensemble:    # FitOptions refuses the pair: the rounds differ from start to start
            raise ValueError("constraint rounds need the starts trained one at a time")
        params, loss, failed, enforced = enforce_constraints(params, static, mech, data, cfg, reg, loss,
                                                  progress)
    # the rounds on a traced branch, after the constraints (which stay at their weights)
    for name, rounds, run in (("branch", cfg.branch_rounds, follow_branch),
                              ("monotone", cfg.monotone_rounds, keep_monotone)):
        if training == "periodic" and rounds and not failed:
            if ensemble:
                raise ValueError(f"{name} rounds need the starts trained one at a time")
            params, loss, failed, more = run(params, static, mech, data, cfg, reg, loss,
                                             enforced, progress)
            enforced = {**enforced, **more}
    out = []
    for i in range(len(keys)):
        if i in failed:
            out.append(Diverged(failed[i]))
            continue
        corr = lane_of(params["corr"], i) if ensemble else params["corr"]
        info = {"training": training, "equation_loss": float(eq_loss[i]),
                "final_loss": float(loss[i]), **enforced}
        if "dP" in params:        # where the fit put each measured orbit's parameter
            dP = lane_of(params["dP"], i) if ensemble else params["dP"]
            offset = np.asarray(data.param_errors.sigma * dP)[:data.measurements().n_orbits]
            info["parameter_offsets"] = [float(x) for x in offset]
        out.append((resolve(UDE(mech, eqx.combine(corr, static))), info))
    return out
