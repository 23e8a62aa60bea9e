"""Training the correction of a UDE: pure loss functions and the optimiser loop.

The stages, in the order :func:`train_ude` runs them:

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
* ``constraints`` (aerofoil, ``constraint_rounds`` > 0): where the periodic fit breaks
  the energy-rising or rest-stability condition, training goes on with the broken penalty
  weighted from the data's misfit, raised each round while it is still broken
  (:func:`_enforce`); a fit that meets both is not touched.
* ``branch`` (aerofoil, ``branch_rounds`` > 0, experimental): the measured orbits asked to
  lie on the branch from the Hopf point, traced in amplitude, with one turn at most
  (:mod:`.branch`, :func:`_branch_rounds`).

Optimisation: Adam, then L-BFGS (optax), all float64. Losses are module-level
functions of (trainable, static, data), compiled once per problem structure.
:func:`train_ensemble` trains many random starts at once, vmapped (:mod:`.optimise`).
"""
from __future__ import annotations


import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._precision import require_float64
from ..models.amplitude import RestLinear, SizeBasis, amplitude_correction, resolve
from ..models.corrections import (MLPCorrection, PolynomialParamCorrection,
                                  RestFreeCorrection, Scaling, feature_scaling)
from ..models.flow import diffrax_samples, rk4_orbit
from ..models.ude import UDE
from .identify import TrainingData, residual_forces
from .optimise import Diverged, descend, lane_of, minimize
from .options import TrainConfig
from .penalties import constraints_for, penalty_sum, regularity_points
from .amplitude_start import start_amplitude
from .branch import BranchData, branch_terms, trace_branch


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


# ---------------------------------------------------------------------------------------
# losses
# ---------------------------------------------------------------------------------------

def equation_loss(params, static, mech, Z, R, penalties=(), reg=None):
    """The correction against the residual forces R at the features Z, plus the penalties
    that act in the equation stage."""
    model = resolve(UDE(mech, eqx.combine(params["corr"], static)))
    corr = model.correction
    pred = jax.vmap(corr)(Z)
    loss = jnp.mean(((pred - R) / corr.scaling.out_scale) ** 2)
    return loss + penalty_sum(penalties, "equation", model, reg)


def _simulate_with_monodromy(model, y0, T, drive, n, sub):
    """One pass of forward-mode autodiff: end state, samples and the monodromy matrix
    (the tangent integration rides along with the primal one, so the orbit is
    integrated once)."""
    def flow(y):
        yT, ys = rk4_orbit(model, y, T, drive, n * sub)
        return yT, (yT, ys)
    M, (yT, ys) = jax.jacfwd(flow, has_aux=True)(y0)
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


def _periodic_objective(model, params, data: TrainingData, cfg: TrainConfig):
    """Closed model orbits through the measured ones, with the measured stability."""
    w_close, w_stab, margin = cfg.closure_weight, cfg.stability_weight, cfg.stability_margin
    sub = cfg.substeps
    n = data.ys.shape[1]
    autonomous = model.mech.autonomous

    def one(ys, y0, T, drive, label):
        if autonomous:
            # an imposed input (the holding control, when given) is periodic in the
            # orbit's own period, which is an unknown here
            drive = eqx.tree_at(lambda d: d.omega, drive, 2.0 * jnp.pi / T)
        yT, sim, M = _simulate_with_monodromy(model, y0, T, drive, n, sub)
        s = model.mech.stability_indicator(M)
        fit = jnp.mean(((sim - ys) / data.y_scale) ** 2)
        close = jnp.sum(((yT - y0) / data.y_scale) ** 2)
        stab = jnp.where(label == 0, 0.0, jax.nn.relu(margin - label * s) ** 2)
        return fit + w_close * close + w_stab * stab

    y0 = data.ys[:, 0, :] + params["dy0"] * data.y_scale
    T = data.period * (1.0 + params["dT"]) if autonomous else data.period
    return jnp.mean(jax.vmap(one)(data.ys, y0, T, data.drive, data.label))


def constrained_periodic_loss(params, static, mech, data: TrainingData, cfg: TrainConfig,
                              reg, constraints, weights):
    """The periodic loss plus the broken constraints' penalties at ``weights`` (an array,
    so that raising them needs no new compilation)."""
    # resolved once: for the amplitude form resolving is a Newton solve
    model = resolve(UDE(mech, eqx.combine(params["corr"], static)))
    extra = sum(w * c.value(model, reg) for c, w in zip(constraints, weights))
    return _periodic_loss_of(model, params, data, cfg, reg) + extra


@eqx.filter_jit
def _misfit_and_constraints(params, static, mech, data, cfg, reg, constraints):
    """The periodic objective without penalties, and every constraint's penalty."""
    model = resolve(UDE(mech, eqx.combine(params["corr"], static)))
    return (_periodic_objective(model, params, data, cfg),
            jnp.stack([c.value(model, reg) for c in constraints]))


def _enforce(params, static, mech, data: TrainingData, cfg: TrainConfig, reg, loss,
             progress=None):
    """Constraints instead of weights (aerofoil, after periodic training). Where the trained
    model breaks one of :data:`~.penalties.CONSTRAINTS` (its penalty above its tolerance),
    training goes on with that penalty added at the weight that makes it count as much as
    the data's misfit at that moment, then ten times more each round while it is still
    broken, for at most ``cfg.constraint_rounds`` rounds. The weight is the data's own
    business, not the user's: a model that meets every constraint is left exactly as it
    was, so data whose fit already has the physics' picture is not touched.

    Returns (params, loss, failed, info): ``descend``'s first three, and info's scalars:
    rounds trained, whether every constraint is met at the end, each constraint's final
    value and weight."""
    constraints = constraints_for(cfg)
    tolerance = np.array([c.tolerance for c in constraints])
    measure = lambda p: _misfit_and_constraints(p, static, mech, data, cfg, reg, constraints)
    weights = np.zeros(len(constraints))
    rounds, failed = 0, {}
    while True:
        misfit, values = (np.asarray(x, float) for x in measure(params))
        broken = values > tolerance
        if not broken.any() or rounds == cfg.constraint_rounds:
            break
        with np.errstate(divide="ignore"):
            first = misfit / values              # where broken, values > 0
        weights = np.where(broken, np.maximum(10.0 * weights, first), weights)
        rounds += 1
        params, loss, failed = descend(
            constrained_periodic_loss, params,
            (static, mech, data, cfg, reg, constraints, jnp.asarray(weights)), lanes=None,
            adam_steps=cfg.adam_steps, lbfgs_steps=cfg.lbfgs_steps, lr=cfg.learning_rate,
            progress=progress, stage=f"constraints, round {rounds}")
        if failed:
            return params, loss, failed, {"constraint_rounds": rounds}
    info = {"constraint_rounds": rounds, "constraints_met": bool(not broken.any())}
    for c, v, w in zip(constraints, values, weights):
        info[f"{c.option}_value"] = float(v)
        info[f"{c.option}_weight"] = float(w)
    return params, loss, failed, info


def branch_loss(params, static, mech, data: TrainingData, cfg: TrainConfig, reg, constraints,
                weights, trace, points, w_branch):
    """The constrained periodic loss plus the branch term (:mod:`.branch`) at ``w_branch``."""
    model = resolve(UDE(mech, eqx.combine(params["corr"], static)))
    extra = sum(w * c.value(model, reg) for c, w in zip(constraints, weights))
    terms = branch_terms(model, trace, *points)
    return _periodic_loss_of(model, params, data, cfg, reg) + extra + w_branch * sum(terms)


@eqx.filter_jit
def _branch_terms_now(params, static, mech, trace, points):
    model = resolve(UDE(mech, eqx.combine(params["corr"], static)))
    return jnp.stack(branch_terms(model, trace, *points))


def _branch_rounds(params, static, mech, data: TrainingData, cfg: TrainConfig, reg, loss,
                   enforced, progress=None):
    """Training on with the branch term (:mod:`.branch`): trace the branch from the Hopf
    point in amplitude, train with its linearised airspeeds, trace again, for at most
    ``cfg.branch_rounds`` rounds. The term's weight makes it count as much as the data's
    misfit in the first round, ten times more each round while its hinges (stability slopes,
    one turn, reach) are broken. A round whose result is worse by the traced (not linearised)
    branch than its start did not stay where the linearisation holds: it is undone and tried
    again with half the steps, at most three times, and then the rounds end.

    Returns (params, loss, failed, info); info's scalars: rounds kept, why they stopped
    early, the final trace's terms, grid points solved, share of points out of reach, and
    the term's weight. (Experimental, off by default: docs/fitting.md.)"""
    constraints = constraints_for(cfg)
    weights = jnp.asarray([enforced.get(f"{c.option}_weight", 0.0) for c in constraints])
    bd = BranchData.of(data)
    P = bd.V
    v_span = max(float(np.ptp(P)), 0.1 * float(P.max()))
    points = (jnp.asarray(bd.V), jnp.asarray(bd.label), v_span, float(bd.amps.max()))
    n = data.ys.shape[1] * cfg.substeps

    def state(p):
        model = resolve(UDE(mech, eqx.combine(p["corr"], static)))
        got = trace_branch(model, bd, n)
        misfit = float(np.asarray(_periodic_objective(model, p, data, cfg)))
        if got is None:
            return None, None, misfit, 0, 1.0
        trace, solved = got
        terms = np.asarray(_branch_terms_now(p, static, mech, trace, points))
        # points beyond the branch's reach count as missed by the whole airspeed span
        unreached = float(np.sum(1.0 - np.asarray(trace.reach))) / len(bd.V)
        return trace, terms, misfit, solved, unreached

    w_b, failed, info = 0.0, {}, {"branch_rounds": 0}
    got = state(params)
    for rnd in range(1, cfg.branch_rounds + 1):
        trace, terms, misfit, solved, unreached = got
        if trace is None:
            info["branch_stop"] = "no branch from a Hopf point"
            break
        total = float(terms.sum())
        if total <= 0 and unreached == 0:
            break
        hinges = float(np.sum(terms[1:] > 1e-12)) + unreached     # (rounding is not broken)
        w_b = misfit / max(total + unreached, 1e-12) if rnd == 1 else (10.0 * w_b if hinges > 0 else w_b)
        before = misfit + w_b * (total + unreached)
        # a trust region by the number of steps: a round the traced branch says is worse
        # is undone and tried again with half the steps, at most three times
        for shrink in (1, 2, 4, 8):
            new, new_loss, failed = descend(
                branch_loss, params,
                (static, mech, data, cfg, reg, constraints, weights, trace, points,
                 jnp.asarray(w_b)), lanes=None,
                adam_steps=cfg.adam_steps // shrink, lbfgs_steps=cfg.lbfgs_steps // shrink,
                lr=cfg.learning_rate, progress=progress, stage=f"branch, round {rnd}")
            cand = None if failed else state(new)
            after = (np.inf if cand is None or cand[0] is None else
                     cand[2] + w_b * (float(cand[1].sum()) + cand[4]))
            failed = {}
            if after <= before:
                break
        if not after <= before:
            info["branch_stop"] = f"round {rnd} undone at every step count"
            break
        params, loss, got = new, new_loss, cand
        info["branch_rounds"] = rnd
    if got[0] is not None:
        trace, terms, misfit, solved, unreached = got
        info.update({f"branch_{name}": float(v) for name, v in
                     zip(("point", "stability", "one_turn", "reach"), terms)})
        info.update(branch_solved=int(solved), branch_unreached=float(unreached),
                    branch_weight=float(w_b))
    return params, loss, failed, info


def periodic_loss(params, static, mech, data: TrainingData, cfg: TrainConfig, reg=None):
    """Closed model orbits through the measured ones with the measured stability, plus the
    penalties that act in the periodic stage."""
    return _periodic_loss_of(resolve(UDE(mech, eqx.combine(params["corr"], static))),
                             params, data, cfg, reg)


def _periodic_loss_of(model, params, data: TrainingData, cfg: TrainConfig, reg):
    return (_periodic_objective(model, params, data, cfg)
            + penalty_sum(cfg.penalties, "periodic", model, reg))


def _mech_leaves(mech):
    """The fitted parameters of a mechanistic model as a tuple of arrays: the base
    model's fitted fields, then each added effect's coefficient vector."""
    base = mech.base
    return (tuple(getattr(base, f) for f in base.fitted)
            + tuple(a.coefficients for a in mech.effects))


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
    if model.mech.autonomous:                  # the period is an unknown too
        params["dT"] = jnp.zeros(data.period.shape)
    params, v = minimize(_mech_periodic_loss, params,
                         (mech, sizes, base, scale, data, cfg),
                         adam_steps=cfg.adam_steps, lbfgs_steps=cfg.lbfgs_steps,
                         lr=cfg.learning_rate, progress=progress, stage="mechanistic")
    refined = _mech_with(mech, sizes, base, scale, params["delta"])
    return UDE(refined), {"loss": v}


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
    is what :func:`train_ude` gives with ``keys[k]``, to rounding. Returns, per key,
    (UDE, info) or the :class:`~.optimise.Diverged` that dropped it."""
    return _train(model, data, list(keys), cfg, training, progress, ensemble=True)


def _train(model: UDE, data: TrainingData, keys: list, cfg: TrainConfig, training: str,
           progress, ensemble: bool) -> list:
    require_float64("train_ude")
    if training not in ("trajectory", "periodic", "equation"):
        raise ValueError(f"unknown training mode {training!r} (trajectory, periodic, equation)")
    cfg = cfg.for_system(model.system)
    # the starts differ only in their network's weights; scaling and structure are shared
    parts = [eqx.partition(c, _trainable_spec(c))
             for c in (new_correction(model, data, k, cfg) for k in keys)]
    static = parts[0][1]
    lanes = len(keys) if ensemble else None
    lead = (len(keys),) if ensemble else ()
    params = {"corr": _stack([p for p, _ in parts]) if ensemble else parts[0][0]}
    mech = model.mech
    Z, R = residual_forces(UDE(mech), data)
    reg = regularity_points(data) if cfg.needs_points() else None
    params, eq_loss, failed = descend(
        equation_loss, params, (static, mech, jnp.asarray(Z), jnp.asarray(R), cfg.penalties,
                                reg),
        lanes=lanes,
        # the amplitude form starts from the orbits' energy balance instead
        adam_steps=0 if cfg.form == "amplitude" else cfg.equation_steps,
        lbfgs_steps=0 if cfg.form == "amplitude" else cfg.equation_lbfgs_steps,
        lr=1e-2, progress=progress, stage="equation")
    loss = eq_loss
    if training == "trajectory":
        params, loss, failed = descend(
            trajectory_loss, params, (static, mech, data, cfg.substeps, cfg.penalties, reg),
            lanes=lanes, adam_steps=cfg.adam_steps, lbfgs_steps=cfg.lbfgs_steps,
            lr=cfg.learning_rate, failed=failed, progress=progress, stage="trajectory")
    elif training == "periodic":
        # initial states and periods as scaled offsets from the measured ones, so one
        # Adam step size suits metres, radians and seconds alike
        params = {"corr": params["corr"], "dy0": jnp.zeros(lead + data.ys[:, 0, :].shape)}
        if model.mech.autonomous:
            params["dT"] = jnp.zeros(lead + data.period.shape)
        params, loss, failed = descend(
            periodic_loss, params, (static, mech, data, cfg, reg), lanes=lanes,
            adam_steps=cfg.adam_steps, lbfgs_steps=cfg.lbfgs_steps, lr=cfg.learning_rate,
            failed=failed, progress=progress, stage="periodic")
    enforced = {}
    if training == "periodic" and cfg.constraint_rounds and not failed:
        if ensemble:    # FitOptions refuses the pair: the rounds differ from start to start
            raise ValueError("constraint rounds need the starts trained one at a time")
        params, loss, failed, enforced = _enforce(params, static, mech, data, cfg, reg, loss,
                                                  progress)
    if training == "periodic" and cfg.branch_rounds and not failed:
        if ensemble:
            raise ValueError("branch rounds need the starts trained one at a time")
        params, loss, failed, more = _branch_rounds(params, static, mech, data, cfg, reg, loss,
                                                    enforced, progress)
        enforced = {**enforced, **more}
    out = []
    for i in range(len(keys)):
        if i in failed:
            out.append(Diverged(failed[i]))
            continue
        corr = lane_of(params["corr"], i) if ensemble else params["corr"]
        out.append((resolve(UDE(mech, eqx.combine(corr, static))),
                    {"training": training, "equation_loss": float(eq_loss[i]),
                     "final_loss": float(loss[i]), **enforced}))
    return out
