"""Training rounds after the periodic stage (aerofoil, periodic training, one start at a
time): each traces or measures the trained model, sets a term's weight from the data's misfit,
and trains on.

* :func:`enforce_constraints` (``constraint_rounds``): the energy-rising and rest-stability
  conditions (:data:`~.penalties.CONSTRAINTS`; with ``constrain_unstable_branch`` the
  unstable-branch condition too) where the fit breaks them.
* :func:`follow_branch` (``branch_rounds``, experimental): the measured orbits on the branch
  from the Hopf point, traced in amplitude, with one turn at most (:mod:`.branch`).
* :func:`keep_monotone` (``monotone_rounds``, experimental): the branch monotone between
  orbits of the same stability and rising above the largest stable one (:mod:`.monotone`).
"""
from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ..models.amplitude import resolve
from ..models.ude import UDE
from .branch import BranchData, branch_terms, trace_branch
from .identify import TrainingData
from .losses import branch_loss, constrained_periodic_loss, monotone_loss, periodic_objective
from .monotone import monotone_term, stretches, trace_stretches
from .optimise import descend
from .options import TrainConfig
from .penalties import constraints_for, regularity_points


@eqx.filter_jit
def _misfit_and_constraints(params, static, mech, data, cfg, reg, constraints):
    """The periodic objective without penalties, and every constraint's penalty."""
    model = resolve(UDE(mech, eqx.combine(params["corr"], static)))
    return (periodic_objective(model, params, data, cfg),
            jnp.stack([c.value(model, reg) for c in constraints]))


@eqx.filter_jit
def _constraint_values(model: UDE, reg, constraints):
    return jnp.stack([c.value(model, reg) for c in constraints])


def broken_constraints(model: UDE, data: TrainingData, cfg: TrainConfig) -> tuple[str, ...]:
    """The conditions of :data:`~.penalties.CONSTRAINTS` that ``model`` breaks on ``data``'s
    measured orbits (its penalty above its tolerance), by option name; none where the
    constraint rounds are off."""
    constraints = constraints_for(cfg.for_system(model.system))
    if not constraints:
        return ()
    values = np.asarray(_constraint_values(model, regularity_points(data.measurements()),
                                           constraints))
    return tuple(c.option for c, v in zip(constraints, values) if v > c.tolerance)


def enforce_constraints(params, static, mech, data: TrainingData, cfg: TrainConfig, reg, loss,
             progress=None):
    """Constraints instead of weights (aerofoil, after periodic training). Where the trained
    model breaks one of :data:`~.penalties.CONSTRAINTS` (its penalty above its tolerance),
    training goes on with that penalty added at the weight that makes it count as much as
    the data's misfit at that moment, then ten times more each round while it is still
    broken, for at most ``cfg.constraint_rounds`` rounds of ``cfg.lbfgs_steps`` L-BFGS
    steps each (after ``cfg.constraint_adam_steps`` Adam steps, none by default: Adam
    restarted at a trained point first moves every weight by about its learning rate,
    undoing part of the fit before it descends again). The weight is the
    data's own business, not the user's: a model that meets every constraint is left
    exactly as it was, so data whose fit already has the physics' picture is not touched.

    A round whose loss is not finite is undone and the rounds end there: the start keeps
    the last model that trained.

    Returns (params, loss, failed, info): ``descend``'s first three (none failed), and info:
    rounds trained, whether every constraint is met at the end, the conditions broken
    before the first round, the data's misfit before the first round and after the last,
    each constraint's final value and weight, and why the rounds stopped early where a
    round was undone."""
    constraints = constraints_for(cfg)
    tolerance = np.array([c.tolerance for c in constraints])
    measure = lambda p: _misfit_and_constraints(p, static, mech, data, cfg, reg, constraints)
    weights = np.zeros(len(constraints))
    rounds, stop, first_misfit, first_broken = 0, None, None, None
    while True:
        misfit, values = (np.asarray(x, float) for x in measure(params))
        broken = values > tolerance
        if first_misfit is None:
            first_misfit, first_broken = float(misfit), broken
        if not broken.any() or rounds == cfg.constraint_rounds:
            break
        with np.errstate(divide="ignore"):
            first = misfit / values              # where broken, values > 0
        tried = np.where(broken, np.maximum(10.0 * weights, first), weights)
        new, new_loss, failed = descend(
            constrained_periodic_loss, params,
            (static, mech, data, cfg, reg, constraints, jnp.asarray(tried)), lanes=None,
            adam_steps=cfg.constraint_adam_steps, lbfgs_steps=cfg.lbfgs_steps,
            lr=cfg.learning_rate,
            progress=progress, stage=f"constraints, round {rounds + 1}")
        if failed:
            # the start is not lost: it keeps the model of the last round that trained, whose
            # broken conditions the info reports (the start's judgement does the rest)
            stop = failed[0]
            break
        params, loss, rounds, weights = new, new_loss, rounds + 1, tried
    # what holding the conditions cost the fit: the data's misfit (the objective without
    # penalties) before the first round and after the last (the same where none ran)
    info = {"constraint_rounds": rounds, "constraints_met": bool(not broken.any()),
            "constraints_broken_before": [c.option for c, b in zip(constraints, first_broken)
                                          if b],
            "misfit_before_rounds": first_misfit, "misfit_after_rounds": float(misfit)}
    if stop is not None:
        info["constraint_stop"] = f"round {rounds + 1} undone ({stop})"
    for c, v, w in zip(constraints, values, weights):
        info[f"{c.option}_value"] = float(v)
        info[f"{c.option}_weight"] = float(w)
    return params, loss, {}, info


def _shortened_round(loss_fn, params, args, cfg: TrainConfig, progress, stage: str, before,
                     shrinks, state, merit):
    """One round with a trust region by the number of steps: trained with ``loss_fn`` at
    the full step counts divided by each of ``shrinks`` in turn, until the traced state
    (``state(params)``, whose first item is None where nothing was traced) has a ``merit``
    no worse than ``before``. Returns (params, loss, state, merit) of the last try; merit
    inf where it failed or traced nothing."""
    for shrink in shrinks:
        new, new_loss, failed = descend(
            loss_fn, params, args, lanes=None, adam_steps=cfg.adam_steps // shrink,
            lbfgs_steps=cfg.lbfgs_steps // shrink, lr=cfg.learning_rate, progress=progress,
            stage=stage)
        cand = None if failed else state(new)
        after = np.inf if cand is None or cand[0] is None else merit(cand)
        if after <= before:
            break
    return new, new_loss, cand, after


@eqx.filter_jit
def _branch_terms_now(params, static, mech, trace, points):
    model = resolve(UDE(mech, eqx.combine(params["corr"], static)))
    return jnp.stack(branch_terms(model, trace, *points))


def follow_branch(params, static, mech, data: TrainingData, cfg: TrainConfig, reg, loss,
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
    v_span = bd.v_span
    points = (jnp.asarray(bd.V), jnp.asarray(bd.label), v_span, float(bd.amps.max()))
    n = data.ys.shape[1] * cfg.substeps

    def state(p):
        model = resolve(UDE(mech, eqx.combine(p["corr"], static)))
        got = trace_branch(model, bd, n)
        misfit = float(np.asarray(periodic_objective(model, p, data, cfg)))
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
        if rnd == 1:
            w_b = misfit / max(total + unreached, 1e-12)
        elif hinges > 0:
            w_b = 10.0 * w_b
        before = misfit + w_b * (total + unreached)
        # a trust region by the number of steps: a round the traced branch says is worse
        # is undone and tried again with half the steps, at most three times
        new, new_loss, cand, after = _shortened_round(
            branch_loss, params, (static, mech, data, cfg, reg, constraints, weights, trace,
                                  points, jnp.asarray(w_b)),
            cfg, progress, f"branch, round {rnd}", before, (1, 2, 4, 8), state,
            lambda c: c[2] + w_b * (float(c[1].sum()) + c[4]))
        failed = {}
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


@eqx.filter_jit
def _monotone_now(params, static, mech, trace, v_span):
    return monotone_term(resolve(UDE(mech, eqx.combine(params["corr"], static))), trace, v_span)


def keep_monotone(params, static, mech, data: TrainingData, cfg: TrainConfig, reg, loss,
                  enforced, progress=None):
    """Training on with the monotone term (:mod:`.monotone`): trace the stretches the labels
    say are monotone, train with their linearised airspeeds, trace again, for at most
    ``cfg.monotone_rounds`` rounds, the constraints kept at the weights their rounds ended
    with. The term's weight makes it count as much as the data's misfit in the first round,
    ten times more each round while it is not met. A round whose result is worse by the
    traced (not linearised) stretches than its start is undone and tried again with half
    the steps, at most twice, and then the rounds end. A step the trace does not reach counts
    in that judgement as one turned a whole airspeed span the wrong way.

    Returns (params, loss, failed, info); info (scalars): stretches planned, rounds kept,
    why they stopped early (and, where a round was undone, the misfit, hinges and unsolved
    steps its last try came to), the final misfit, hinges and unsolved steps, grid points
    planned and solved, and the weight the kept model trained with. (Experimental, off by default:
    docs/fitting.md.)"""
    constraints = constraints_for(cfg)
    weights = jnp.asarray([enforced.get(f"{c.option}_weight", 0.0) for c in constraints])
    bd = BranchData.of(data)
    plan = stretches(bd)
    v_span = bd.v_span
    n = data.ys.shape[1] * cfg.substeps

    def state(p):
        """(trace, hinges, unsolved steps, misfit, points solved per stretch)."""
        model = resolve(UDE(mech, eqx.combine(p["corr"], static)))
        misfit = float(np.asarray(periodic_objective(model, p, data, cfg)))
        got = trace_stretches(model, data, bd, plan, n, p) if plan else None
        if got is None:
            return None, None, None, misfit, []
        trace, solved = got
        hinges = float(_monotone_now(p, static, mech, trace, v_span))
        return trace, hinges, sum(len(s.amps) - max(k, 1) for s, k in zip(plan, solved)), \
            misfit, solved

    def merit(st, w):
        # a step the trace does not reach counts as one turned a whole airspeed span against
        # its direction: a round must not meet the term by breaking the trace, and one that
        # takes the trace further is better for it
        return st[3] + w * (st[1] + st[2])

    w_m, w_kept, info = 0.0, 0.0, {"monotone_rounds": 0, "monotone_stretches": len(plan)}
    got = state(params)
    for rnd in range(1, cfg.monotone_rounds + 1):
        trace, hinges, _, misfit, _ = got
        if trace is None:
            info["monotone_stop"] = ("no stretch between orbits of one stability" if not plan
                                     else "no stretch traced")
            break
        if hinges <= 0:          # (steps not reached give the training nothing to move)
            break
        w_m = misfit / hinges if rnd == 1 else 10.0 * w_m
        before = merit(got, w_m)
        # a trust region by the number of steps, as in the branch rounds
        new, new_loss, cand, after = _shortened_round(
            monotone_loss, params, (static, mech, data, cfg, reg, constraints, weights, trace,
                                    v_span, jnp.asarray(w_m)),
            cfg, progress, f"monotone, round {rnd}", before, (1, 2, 4), state,
            lambda c: merit(c, w_m))
        if not after <= before:
            info["monotone_stop"] = f"round {rnd} undone at every step count"
            if cand is not None and cand[0] is not None:     # what the last try came to
                info.update(monotone_tried_misfit=cand[3], monotone_tried_hinges=cand[1],
                            monotone_tried_unsolved=cand[2])
            break
        params, loss, got, w_kept = new, new_loss, cand, w_m
        info["monotone_rounds"] = rnd
    trace, hinges, unsolved, misfit, solved = got
    # (scalars: what a start's record keeps; the weight the kept model trained with)
    info.update(monotone_misfit=misfit, monotone_weight=float(w_kept),
                monotone_points=sum(len(s.amps) for s in plan), monotone_solved=sum(solved))
    if trace is not None:
        info.update(monotone_hinges=hinges, monotone_unsolved=unsolved)
    return params, loss, {}, info
