"""The losses a UDE's correction is trained on: pure functions of (trainable, static, data),
compiled once per problem structure.

* :func:`equation_loss`: the correction against the residual force the mechanistic model
  leaves on every sample of the averaged orbits (no simulation).
* :func:`trajectory_loss` (the paper's): one-period trajectories from the measured states.
* :func:`periodic_loss`: closed model orbits through the measured ones, each with its own
  initial state and (aerofoil) period as unknowns, with the stability the data says; stability
  enters through the sign of the characteristic polynomial of the monodromy matrix at 1 (the
  aerofoil's trivial multiplier factored out), which changes sign exactly where a real
  multiplier crosses 1, as at a fold: smooth and with no eigen-decomposition.
* :func:`constrained_periodic_loss`, :func:`branch_loss` and :func:`monotone_loss`: the
  periodic loss with the terms of the constraint, branch and monotone rounds (:mod:`.rounds`).
"""
from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from ..models.amplitude import resolve
from ..models.flow import diffrax_samples, rk4_orbit_monodromy
from ..models.ude import UDE
from .branch import branch_terms
from .identify import TrainingData
from .monotone import monotone_term
from .options import TrainConfig
from .penalties import penalty_sum


def equation_loss(params, static, mech, Z, R, penalties=(), reg=None):
    """The correction against the residual forces R at the features Z, plus the penalties
    that act in the equation stage."""
    model = resolve(UDE(mech, eqx.combine(params["corr"], static)))
    corr = model.correction
    pred = jax.vmap(corr)(Z)
    loss = jnp.mean(((pred - R) / corr.scaling.out_scale) ** 2)
    return loss + penalty_sum(penalties, "equation", model, reg)


def _simulate_with_monodromy(model, y0, T, drive, n, sub):
    """End state, samples and the monodromy matrix (:func:`rk4_orbit_monodromy`: the
    derivative of the discrete flow, from the Jacobians at every Runge-Kutta stage)."""
    yT, ys, M = rk4_orbit_monodromy(model, y0, T, drive, n * sub)
    return yT, ys[::sub], M


def trajectory_loss(params, static, mech, data: TrainingData, sub: int, penalties=(),
                    reg=None):
    """One-period trajectories from the measured states against the measured orbits (the
    paper's loss), plus the penalties that act in the trajectory stage."""
    model = resolve(UDE(mech, eqx.combine(params["corr"], static)))
    return (_trajectory_error(model, data, sub)
            + penalty_sum(penalties, "trajectory", model, reg))


def _trajectory_error(model, data: TrainingData, sub: int):
    n = data.ys.shape[1]

    def one(ys, T, drive):
        sim = diffrax_samples(model, ys[0], T, drive, n, sub)
        return jnp.mean(((sim - ys) / data.y_scale) ** 2)

    return jnp.mean(jax.vmap(one)(data.ys, data.period, data.drive))


class OrbitTerms(eqx.Module):
    """Each orbit's parts of the periodic objective, one entry per orbit."""
    fit: jax.Array          # mean square misfit of the samples over the state scales
    closure: jax.Array      # end state against start state, squared, over the scales
    indicator: jax.Array    # model.mech.stability_indicator: > 0 stable, < 0 unstable
    # (n_orbits, 2) model.mech.secondary_indicators: > 0 while no multiplier has passed -1
    # and no complex pair has crossed the unit circle; +inf (nothing to hold) for a model
    # whose fits do not hold them (holds_secondary_tests)
    secondary: jax.Array
    prior: jax.Array        # the parameter offset's cost (0 where the parameter is exact)


def orbit_terms(model, params, data: TrainingData, cfg: TrainConfig) -> OrbitTerms:
    """Every orbit of ``data`` simulated from its unknowns in ``params`` (initial state,
    period, parameter offset) over one period: how far it is from the measured orbit, how
    far from closing, and how stable it is."""
    sub = cfg.substeps
    n = data.ys.shape[1]
    autonomous = model.mech.autonomous
    mech = model.mech

    def secondary_tests(M, fold):
        if mech.holds_secondary_tests:
            return mech.secondary_indicators(M, fold)
        return jnp.full(2, jnp.inf)

    state_weight = (jnp.ones(data.ys.shape[::2]) if data.state_weight is None
                    else data.state_weight)

    def one(ys, y0, T, drive, sw):
        if autonomous:
            # an imposed input (the holding control, when given) is periodic in the
            # orbit's own period, which is an unknown here
            drive = eqx.tree_at(lambda d: d.omega, drive, 2.0 * jnp.pi / T)
        yT, sim, M = _simulate_with_monodromy(model, y0, T, drive, n, sub)
        fit = jnp.mean(((sim - ys) / data.y_scale) ** 2 * sw) / jnp.mean(sw)
        close = jnp.sum(((yT - y0) / data.y_scale) ** 2)
        fold = mech.stability_indicator(M)
        return fit, close, fold, secondary_tests(M, fold)

    y0 = data.ys[:, 0, :] + params["dy0"] * data.y_scale
    T = data.period * (1.0 + params["dT"]) if autonomous else data.period
    drive, prior = data.drive, jnp.zeros(data.period.shape)
    if "dP" in params:            # errors in the measured parameters (.parameter_errors)
        errors = data.param_errors
        drive = eqx.tree_at(lambda d: d.param, drive, drive.param + errors.sigma * params["dP"])
        prior = errors.cost * params["dP"] ** 2
    fit, close, indicator, secondary = jax.vmap(one)(data.ys, y0, T, drive, state_weight)
    return OrbitTerms(fit, close, indicator, secondary, prior)


def periodic_objective(model, params, data: TrainingData, cfg: TrainConfig):
    """Closed model orbits through the measured ones, with the measured stability."""
    return objective_of(orbit_terms(model, params, data, cfg), data, cfg)


def objective_of(t: OrbitTerms, data: TrainingData, cfg: TrainConfig):
    """The periodic objective from each orbit's terms (by shooting, or by collocation:
    :mod:`.collocation`): misfit, closure, the measured stability held at its margin."""
    margin = cfg.stability_margin
    if data.margin is not None:     # the data's own (analysis.margins)
        margin = jnp.where(jnp.isnan(data.margin), margin, data.margin)
    stab = jnp.where(data.label == 0, 0.0,
                     jax.nn.relu(margin - data.label * t.indicator) ** 2)
    # a stable orbit has every multiplier inside the unit circle, not only none past 1: the
    # two other ways out held at the configured margin (the data measures neither), where
    # the model's kind holds them (+inf tests elsewhere cost nothing)
    stab = stab + jnp.where(data.label > 0, jnp.sum(
        jax.nn.relu(cfg.stability_margin - t.secondary) ** 2, axis=-1), 0.0)
    per = t.fit + cfg.closure_weight * t.closure + cfg.stability_weight * stab + t.prior
    if data.weight is None:
        return jnp.mean(per)
    return jnp.sum(data.weight * per) / jnp.sum(data.weight)


def orbit_unknowns(data: TrainingData, autonomous: bool, lead: tuple = ()) -> dict:
    """The periodic stage's unknowns besides the model, all scaled offsets from the
    measured values (so one Adam step size suits metres, radians, seconds and m/s): every
    orbit's initial state, its period where the system is autonomous, its parameter where
    the data says it may be in error. ``lead``: a leading ensemble axis."""
    return {"dy0": jnp.zeros(lead + data.ys[:, 0, :].shape),
            **orbit_offsets(data, autonomous, lead)}


def orbit_offsets(data: TrainingData, autonomous: bool, lead: tuple = ()) -> dict:
    """Every orbit's period offset where the system is autonomous and its parameter offset
    where the data says it may be in error (scaled; shooting and collocation share them)."""
    unknowns = {}
    if autonomous:
        unknowns["dT"] = jnp.zeros(lead + data.period.shape)
    if data.param_errors is not None:
        unknowns["dP"] = jnp.zeros(lead + data.period.shape)
    return unknowns


def weighted_constraints(model, reg, constraints, weights):
    """The constraints' penalties at ``weights``; one weighing 0 is not evaluated (a branch,
    not a product: some, as the harmonic balance, cost as much as the orbits)."""
    return sum(jax.lax.cond(w > 0, lambda c=c, w=w: w * c.value(model, reg),
                            lambda: jnp.zeros(()))
               for c, w in zip(constraints, weights))


def constrained_periodic_loss(params, static, mech, data: TrainingData, cfg: TrainConfig,
                              reg, constraints, weights):
    """The periodic loss plus the broken constraints' penalties at ``weights`` (an array,
    so that raising them needs no new compilation)."""
    # resolved once: for the amplitude form resolving is a Newton solve
    model = resolve(UDE(mech, eqx.combine(params["corr"], static)))
    extra = weighted_constraints(model, reg, constraints, weights)
    return periodic_loss_of(model, params, data, cfg, reg) + extra


def branch_loss(params, static, mech, data: TrainingData, cfg: TrainConfig, reg, constraints,
                weights, trace, points, w_branch):
    """The constrained periodic loss plus the branch term (:mod:`.branch`) at ``w_branch``."""
    model = resolve(UDE(mech, eqx.combine(params["corr"], static)))
    extra = weighted_constraints(model, reg, constraints, weights)
    terms = branch_terms(model, trace, *points)
    return periodic_loss_of(model, params, data, cfg, reg) + extra + w_branch * sum(terms)


def monotone_loss(params, static, mech, data: TrainingData, cfg: TrainConfig, reg, constraints,
                  weights, trace, v_span, w_monotone):
    """The constrained periodic loss plus the monotone term (:mod:`.monotone`) at
    ``w_monotone``."""
    model = resolve(UDE(mech, eqx.combine(params["corr"], static)))
    extra = weighted_constraints(model, reg, constraints, weights)
    return (periodic_loss_of(model, params, data, cfg, reg) + extra
            + w_monotone * monotone_term(model, trace, v_span))


def periodic_loss(params, static, mech, data: TrainingData, cfg: TrainConfig, reg=None):
    """Closed model orbits through the measured ones with the measured stability, plus the
    penalties that act in the periodic stage."""
    return periodic_loss_of(resolve(UDE(mech, eqx.combine(params["corr"], static))),
                             params, data, cfg, reg)


def periodic_loss_of(model, params, data: TrainingData, cfg: TrainConfig, reg):
    return (periodic_objective(model, params, data, cfg)
            + penalty_sum(cfg.penalties, "periodic", model, reg))
