"""Branch rounds (``--branch-rounds``, training.branch): the model's branch from the Hopf
point traced in amplitude, and its airspeeds as first-order functions of the parameters,
checked against the pseudo-arclength tracer and against tracing again; and the rounds on a
model with a second fold planted above the data."""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tests.ude_corrections import LargeSwingFeed, SpeedDamping
from tests.ude_fixtures import write_truth_campaign
from ude_fit import UDE, identify, load, training_data
from ude_fit.analysis.continuation import trace_flutter
from ude_fit.training.branch import (BranchData, branch_airspeeds, branch_terms, one_turn,
                                     trace_branch)
from ude_fit.training.options import FitOptions, TrainConfig
from ude_fit.training.penalties import regularity_points
from ude_fit.training.rounds import follow_branch

jax.config.update("jax_enable_x64", True)

# the planted round trains 60 steps on the 3 orbits and traces the branch twice
pytestmark = pytest.mark.minutes(1)

N_STEPS = 128        # RK4 steps per period, as training takes them (32 samples x 4)
PLANTED = 1.0        # LargeSwingFeed's k: the stable branch turns back near 1.3 x the top orbit


@pytest.fixture(scope="module")
def problem(tmp_path_factory):
    path = tmp_path_factory.mktemp("branch") / "f.h5"
    write_truth_campaign(path, "flutter", airspeeds=(18.0, 21.0, 23.6))
    data = training_data(load([path], "flutter"))
    mech, _ = identify(data, "flutter")
    bd = BranchData.of(data, n_grid=16)     # (32 in training; fewer keeps the test short)
    trace, solved = trace_branch(UDE(mech), bd, N_STEPS)
    return data, mech, bd, trace, solved


def test_the_branch_in_amplitude_is_the_continuations_branch(problem):
    data, mech, bd, trace, solved = problem
    # the identified model has the rig's subcritical picture: the branch from the Hopf
    # point falls in airspeed to one fold, then rises, and amplitude grows along it
    assert solved == len(bd.grid)
    V = np.asarray(trace.V)
    k = int(np.argmin(V))
    assert 0 < k < len(V) - 1
    assert np.all(np.diff(V[:k + 1]) < 0) and np.all(np.diff(V[k:]) > 0)
    ref = trace_flutter(UDE(mech), v_range=bd.v_range, amp_max=1.5 * bd.grid[-1],
                        scales=bd.scales, n=N_STEPS)
    assert np.all(np.diff(ref.amplitude) > 0)
    # (the continuation stops where the stable branch leaves the diagram's window)
    inside = bd.grid <= ref.amplitude.max()
    assert inside.sum() >= 10
    V_ref = np.interp(bd.grid[inside], ref.amplitude, ref.param)
    # the continuation's points are a few per m/s apart: linear interpolation between them
    # is good to a few thousandths of the airspeed
    np.testing.assert_allclose(V[inside], V_ref, atol=0.02)
    # and the hopf point is where the amplitude grid starts
    assert abs(V[0] - ref.hopf["param"]) < 0.01


def test_the_linearised_airspeeds_are_the_first_order_change(problem):
    data, mech, bd, trace, solved = problem
    for k in (2e-2, -2e-2):
        model = UDE(mech, SpeedDamping(jnp.asarray(k)))
        V_lin = np.asarray(branch_airspeeds(model, trace))
        new, n_new = trace_branch(model, bd, N_STEPS)
        m = min(solved, n_new)
        change = np.asarray(new.V)[:m] - np.asarray(trace.V)[:m]
        assert np.max(np.abs(change)) > 0.05                  # the change is not nothing
        # first order: the error is second order in the change
        err = np.abs(V_lin[:m] - np.asarray(new.V)[:m])
        assert np.max(err) < 0.05 * np.max(np.abs(change))


def test_the_traced_model_gives_its_own_airspeeds(problem):
    data, mech, bd, trace, solved = problem
    np.testing.assert_allclose(np.asarray(branch_airspeeds(UDE(mech), trace))[:solved],
                               np.asarray(trace.V)[:solved], atol=1e-8)


@pytest.mark.parametrize("slope, zero", [
    ([-3.0, -1.0, 0.5, 2.0, 4.0], True),      # falls to one fold, then rises
    ([1.0, 2.0, 0.1], True),                  # only rises (supercritical)
    ([-1.0, -2.0], True),                     # only falls (within the grid)
    ([-1.0, 2.0, -1.0, 2.0], False),          # two turns
    ([1.0, -0.5, 2.0], False),                # a hook at the start
])
def test_one_turn_is_zero_exactly_on_branches_with_at_most_one_fold(slope, zero):
    v = float(one_turn(jnp.asarray(slope)))
    assert (v == 0.0) == zero
    if not zero:
        # the cheapest split: the smaller of the wrong-signed runs' squares
        assert v > 0


def test_one_turn_charges_the_cheapest_split():
    # the split after the first fall charges the later 0.2 fall (0.04), cheaper than
    # charging the 0.5 rise (0.25) or the 1.0 fall (1.0)
    assert float(one_turn(jnp.asarray([-1.0, 0.5, -0.2, 1.0]))) == pytest.approx(
        min(0.5 ** 2, 0.2 ** 2) / 4)


def _one_turn_traced(model, bd):
    """The one-turn term of ``model``'s branch, traced from scratch on the rounds' grid."""
    trace, solved = trace_branch(model, bd, N_STEPS)
    a_top = float(bd.amps.max())
    terms = branch_terms(model, trace, jnp.asarray(bd.V), jnp.asarray(bd.label), bd.v_span,
                         a_top)
    return float(terms[2]), solved


def test_the_rounds_take_away_the_second_fold_the_data_cannot_see(problem):
    """follow_branch end to end: the identified model with the planted feed as the trained
    correction (its k the one weight), the measured orbits' unknowns at the measurement."""
    data, mech, *_ = problem
    bd = BranchData.of(data)                 # the rounds' own grid
    planted = UDE(mech, LargeSwingFeed(jnp.asarray(PLANTED)))
    was, solved = _one_turn_traced(planted, bd)
    assert was > 0 and solved == len(bd.grid)      # a second turn inside the grid
    cfg = dataclasses.replace(TrainConfig(adam_steps=20, lbfgs_steps=40, branch_rounds=1)
                              .for_system("flutter"), constraint_rounds=0)
    corr, static = eqx.partition(LargeSwingFeed(jnp.asarray(PLANTED)), eqx.is_inexact_array)
    params = {"corr": corr, "dy0": jnp.zeros(data.ys[:, 0, :].shape),
              "dT": jnp.zeros(data.period.shape)}
    new, _, failed, info = follow_branch(params, static, mech, data, cfg,
                                         regularity_points(data), None, {})
    assert not failed and info["branch_rounds"] >= 1, info
    assert info["branch_weight"] > 0
    # the feed the data cannot see is what the rounds took away, and the second turn traced
    # from scratch shrank (measured: k 1 -> 0.92 in one round, the term 3.0e-4 -> 4.9e-6)
    k = float(new["corr"].k)
    assert 0 <= k < PLANTED
    now, _ = _one_turn_traced(UDE(mech, LargeSwingFeed(jnp.asarray(k))), bd)
    assert now < 0.1 * was


@pytest.mark.parametrize("fields, message", [
    (dict(system="oscillator"), "applies to --system flutter only"),
    (dict(system="flutter", training="trajectory"), "applies to --training periodic only"),
    (dict(system="flutter", starts_together=True), "one at a time"),
])
def test_branch_rounds_are_refused_where_they_do_not_apply(fields, message):
    with pytest.raises(ValueError, match=message):
        FitOptions(train=TrainConfig(branch_rounds=2), **fields)
