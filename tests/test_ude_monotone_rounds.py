"""Monotone rounds (``--monotone-rounds``, training.monotone): the stretches the measured
orbits' stability says are monotone, traced from the fitted orbits in amplitude, checked
against the pseudo-arclength tracer; and the rounds on a model with a second fold planted
above the data, where the data cannot see it."""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tests.ude_corrections import LargeSwingFeed
from tests.ude_fixtures import write_truth_campaign
from ude_fit import UDE, identify, load, training_data
from ude_fit.analysis.continuation import trace_flutter
from ude_fit.training.branch import BranchData
from ude_fit.training.monotone import (ABOVE_REACH, monotone_term, stretch_airspeeds,
                                       stretches, trace_stretches, turning_against)
from ude_fit.training.options import FitOptions, TrainConfig
from ude_fit.training.penalties import regularity_points
from ude_fit.training.rounds import keep_monotone

jax.config.update("jax_enable_x64", True)

# the planted rounds train about 200 steps on the 4 orbits, tracing the stretches each round
pytestmark = pytest.mark.minutes(1)

N_STEPS = 128        # RK4 steps per period, as training takes them (32 samples x 4)
V_SPAN = 2.6         # the campaign's airspeed span, as the rounds take it
PLANTED = 1.0        # LargeSwingFeed's k: the stable branch turns back near 1.3 x the top orbit


@pytest.fixture(scope="module")
def problem(tmp_path_factory):
    path = tmp_path_factory.mktemp("monotone") / "f.h5"
    write_truth_campaign(path, "flutter", airspeeds=(21.0, 23.6))
    data = training_data(load([path], "flutter"))
    mech, _ = identify(data, "flutter")
    bd = BranchData.of(data)
    return data, mech, bd, stretches(bd)


def test_the_stretches_are_the_ones_the_labels_imply(problem):
    data, mech, bd, plan = problem
    # 2 unstable and 2 stable orbits: one stretch each between them, falling and rising, and
    # one rising above the largest (stable) orbit
    assert [s.direction for s in plan] == [-1.0, 1.0, 1.0]
    for s in plan[:2]:
        same = np.flatnonzero(bd.label == s.direction)
        above = same[bd.amps[same] > bd.amps[s.start]]
        assert s.amps[0] == bd.amps[s.start] and s.amps[-1] == bd.amps[above].min()
    assert plan[-1].amps[-1] == pytest.approx(ABOVE_REACH * bd.amps.max())


def test_unknown_stability_implies_no_stretch_and_an_unstable_top_no_rise(problem):
    data, mech, bd, plan = problem
    top = int(np.argmax(bd.amps))
    unknown = dataclasses.replace(bd, label=np.where(np.arange(len(bd.label)) == top, 0.0,
                                                     bd.label))
    got = stretches(unknown)
    assert [s.direction for s in got] == [-1.0]           # no rise, no stable pair
    flipped = dataclasses.replace(bd, label=np.where(np.arange(len(bd.label)) == top, -1.0,
                                                     bd.label))
    assert all(s.amps[-1] <= bd.amps.max() for s in stretches(flipped))


@pytest.fixture(scope="module")
def traced(problem):
    data, mech, bd, plan = problem
    return trace_stretches(UDE(mech), data, bd, plan, N_STEPS)


def test_the_stretches_lie_on_the_continuations_branch(problem, traced):
    data, mech, bd, plan = problem
    trace, solved = traced
    assert solved == [len(s.amps) for s in plan]
    # the identified model has the rig's picture, one fold between the unstable and the
    # stable orbits: every stretch is monotone as its labels say, and the term is zero
    assert float(monotone_term(UDE(mech), trace, V_SPAN)) == 0.0
    # (a window wide enough for the fold, 16.8 m/s, below this campaign's airspeeds)
    ref = trace_flutter(UDE(mech), v_range=(10.0, 35.0), amp_max=1.5 * bd.amps.max(),
                        scales=bd.scales, n=N_STEPS)
    amps, V = np.asarray(trace.amps), np.asarray(trace.V)
    inside = amps <= ref.amplitude.max()
    assert inside.sum() >= 12
    # the stable and unstable sides in amplitude: the continuation's branch is single-valued
    # in amplitude, rising from the Hopf point to its fold and then the stable side
    np.testing.assert_allclose(V[inside], np.interp(amps[inside], ref.amplitude, ref.param),
                               atol=0.03)


def test_the_traced_model_gives_its_own_airspeeds(problem, traced):
    data, mech, bd, plan = problem
    trace, _ = traced
    np.testing.assert_allclose(np.asarray(stretch_airspeeds(UDE(mech), trace)),
                               np.asarray(trace.V), atol=1e-8)


def test_turning_against_charges_the_steps_against_their_direction(traced):
    trace, _ = traced
    lo, direction = np.asarray(trace.lo), np.asarray(trace.direction)
    assert direction[0] == -1.0 and direction[-1] == 1.0
    # a bump of 1 inside the falling stretch: its rise is charged, the fall after it is not
    V = np.zeros(len(trace.V))
    V[lo[0] + 1] = 1.0
    assert float(turning_against(jnp.asarray(V), trace, 2.0)) == pytest.approx(0.25)
    # a dip of 1 inside the last (rising) stretch: its fall is charged, the rise after it not
    V = np.zeros(len(trace.V))
    V[lo[-1]] = -1.0
    assert float(turning_against(jnp.asarray(V), trace, 2.0)) == pytest.approx(0.25)
    # steps across two stretches are not steps
    assert set(np.diff(lo)) <= {1, 2}


@pytest.fixture(scope="module")
def planted(problem):
    """keep_monotone on the identified model with the planted feed as the trained
    correction (its k the one weight), the measured orbits' unknowns at the measurement."""
    data, mech, bd, plan = problem
    cfg = dataclasses.replace(TrainConfig(adam_steps=20, lbfgs_steps=40, monotone_rounds=3)
                              .for_system("flutter"), constraint_rounds=0)
    corr, static = eqx.partition(LargeSwingFeed(jnp.asarray(PLANTED)), eqx.is_inexact_array)
    params = {"corr": corr, "dy0": jnp.zeros(data.ys[:, 0, :].shape),
              "dT": jnp.zeros(data.period.shape)}
    before = trace_stretches(UDE(mech, LargeSwingFeed(jnp.asarray(PLANTED))), data, bd, plan,
                             N_STEPS, params)
    new, _, failed, info = keep_monotone(params, static, mech, data, cfg,
                                         regularity_points(data), None, {})
    return before, new, failed, info


def test_the_planted_fold_is_charged(problem, planted):
    data, mech, bd, plan = problem
    (trace, solved), *_ = planted
    assert solved == [len(s.amps) for s in plan]
    top = np.asarray(trace.V)[-len(plan[-1].amps):]
    # the stable branch above the largest orbit turns back inside the reach
    k = int(np.argmax(top))
    assert 0 < k < len(top) - 1 and top[-1] < top[k]
    assert float(monotone_term(UDE(mech, LargeSwingFeed(jnp.asarray(PLANTED))), trace,
                               V_SPAN)) > 0


def _hinges(model, data, bd, plan, params):
    trace, solved = trace_stretches(model, data, bd, plan, N_STEPS, params)
    return float(monotone_term(model, trace, V_SPAN)), solved


def test_the_rounds_push_out_the_fold_the_data_cannot_see(problem, planted):
    data, mech, bd, plan = problem
    _, new, failed, info = planted
    assert not failed and info["monotone_rounds"] >= 2, info
    assert info["monotone_weight"] > 0 and info["monotone_solved"] == info["monotone_points"]
    assert info["monotone_unsolved"] == 0
    # the feed the data cannot see is what the rounds took away (the weight is trained on
    # the data and the term alone)
    k = float(new["corr"].k)
    assert 0 <= k < 0.8 * PLANTED
    # traced again from scratch, before and after: the turn against the labels shrank
    was, _ = _hinges(UDE(mech, LargeSwingFeed(jnp.asarray(PLANTED))), data, bd, plan, None)
    now, solved = _hinges(UDE(mech, LargeSwingFeed(jnp.asarray(k))), data, bd, plan, new)
    assert solved == [len(s.amps) for s in plan]
    assert now < 0.25 * was


@pytest.mark.parametrize("fields, message", [
    (dict(system="oscillator"), "applies to --system flutter only"),
    (dict(system="flutter", training="trajectory"), "applies to --training periodic only"),
    (dict(system="flutter", starts_together=True), "one at a time"),
    (dict(system="flutter", approximator="gp"), "apply to --approximator nn only"),
])
def test_monotone_rounds_are_refused_where_they_do_not_apply(fields, message):
    with pytest.raises(ValueError, match=message):
        FitOptions(train=TrainConfig(monotone_rounds=2), **fields)


@pytest.mark.parametrize("bad", [-1, 1.5, True])
def test_a_bad_round_count_is_named(bad):
    with pytest.raises(ValueError, match="monotone_rounds"):
        TrainConfig(monotone_rounds=bad)
