"""Constraints instead of weights (``--constraint-rounds``,
training.rounds.enforce_constraints): a fit that breaks the energy-rising or rest-stability
condition trains on with the broken penalty at a weight set from the data's misfit, raised
tenfold per round while it is still broken; a fit that meets both is left exactly as it
was."""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tests.ude_corrections import SpeedDamping
from tests.ude_fixtures import write_truth_campaign
from ude_fit import UDE, identify, load, training_data
from ude_fit.report.markdown import _constraint_rounds
from ude_fit.training.options import FitOptions, TrainConfig
from ude_fit.training.penalties import (constraints_for, EnergyRising, RestStability,
                                        regularity_points)
from ude_fit.training.rounds import (_misfit_and_constraints, broken_constraints,
                                    enforce_constraints)

jax.config.update("jax_enable_x64", True)

pytestmark = pytest.mark.minutes(2)   # CI order: tests/conftest.py


@pytest.fixture(scope="module")
def problem(tmp_path_factory):
    path = tmp_path_factory.mktemp("constraints") / "f.h5"
    write_truth_campaign(path, "flutter", airspeeds=(18.0, 21.0, 23.6))
    data = training_data(load([path], "flutter"))
    mech, _ = identify(data, "flutter")
    cfg = TrainConfig(adam_steps=50, lbfgs_steps=20, constraint_rounds=3).for_system("flutter")
    return data, mech, cfg, regularity_points(data)


def _unknowns(data, k):
    """SpeedDamping(k) split for training, with the measured orbits' own initial states and
    periods: (params, static)."""
    trainable, static = eqx.partition(SpeedDamping(jnp.asarray(k)), eqx.is_inexact_array)
    return ({"corr": trainable, "dy0": jnp.zeros(data.ys[:, 0, :].shape),
             "dT": jnp.zeros(data.period.shape)}, static)


def _enforced(problem, k, **cfg_fields):
    data, mech, cfg, reg = problem
    cfg = dataclasses.replace(cfg, **cfg_fields)
    params, static = _unknowns(data, k)
    before = [float(c.value(UDE(mech, SpeedDamping(jnp.asarray(k))), reg))
              for c in constraints_for(cfg)]
    out, _, failed, info = enforce_constraints(params, static, mech, data, cfg, reg,
                                               np.array([np.nan]))
    return before, float(out["corr"].k), failed, info, {key: out[key] for key in ("dy0", "dT")}


def test_the_rest_is_held_stable_at_each_unstable_orbits_airspeed(problem):
    data, _, _, reg = problem
    P, label = np.asarray(data.drive.param), np.asarray(data.label)
    assert np.any(label < 0)
    assert np.array_equal(np.asarray(reg.surrounded_V), np.unique(P[label < 0]))


def test_a_model_is_checked_against_every_condition(problem):
    # what the guide rounds ask of each round's model (the conditions a round's training
    # weighs at 0 included): SpeedDamping's Hopf point at k = 0.5, 1 and -50 (below)
    data, mech, cfg, _ = problem
    broken = lambda k: broken_constraints(UDE(mech, SpeedDamping(jnp.asarray(k))), data, cfg)
    assert broken(0.5) == ()
    assert broken(1.0) == ("rest-stability",)
    assert broken(-50.0) == ("energy-rising", "rest-stability")
    assert broken_constraints(UDE(mech, SpeedDamping(jnp.asarray(1.0))), data,
                              dataclasses.replace(cfg, constraint_rounds=0)) == ()


def test_a_fit_that_meets_the_constraints_is_left_as_it_is(problem):
    # the mechanistic model identified from the rig's own orbits, plus a correction that
    # feeds energy in as the airspeed grows: both conditions hold (its Hopf point 23.92 m/s,
    # beyond the highest unstable orbit, 23.6; with k = 1 it falls to 23.55, below it, and
    # the equilibrium that orbit surrounds would be unstable)
    before, k, failed, info, _ = _enforced(problem, 0.5)
    assert all(v <= c.tolerance for v, c in zip(before, constraints_for(problem[2])))
    assert not failed
    assert info["constraint_rounds"] == 0 and info["constraints_met"]
    assert info["constraints_broken_before"] == []
    assert info["misfit_before_rounds"] == info["misfit_after_rounds"]
    assert k == 0.5                              # not trained: exactly as it was
    assert info["energy-rising_weight"] == 0.0 and info["rest-stability_weight"] == 0.0


def _misfit(problem, k, offsets=None):
    """The data's misfit (the periodic objective without penalties) of SpeedDamping(k), at
    the orbits' initial states and periods ``offsets`` (the measured ones by default)."""
    data, mech, cfg, reg = problem
    params, static = _unknowns(data, k)
    return float(_misfit_and_constraints({**params, **(offsets or {})}, static, mech, data,
                                         cfg, reg, constraints_for(cfg))[0])


def test_a_broken_condition_is_enforced_without_a_weight_from_the_user(problem):
    before, k, failed, info, offsets = _enforced(problem, -50.0)
    rising, rest = before
    assert rising > 100 * EnergyRising(1.0).tolerance          # broken, by far
    assert rest > 100 * RestStability(1.0).tolerance           # and so is the other
    assert not failed
    assert info["constraint_rounds"] >= 1
    # what the rounds cost (here they mend a model far off the orbits): the misfit before
    # them is the untrained model's, the one after them the trained model's
    assert info["constraints_broken_before"] == ["energy-rising", "rest-stability"]
    assert info["misfit_before_rounds"] == pytest.approx(_misfit(problem, -50.0), rel=1e-9)
    assert info["misfit_after_rounds"] == pytest.approx(
        _misfit(problem, k, offsets), rel=1e-9)
    assert info["misfit_after_rounds"] < info["misfit_before_rounds"]
    assert info["energy-rising_weight"] > 0
    # trained on until the work per cycle rises with the airspeed again (or nearly)
    assert k > -50.0
    assert info["energy-rising_value"] < 0.01 * rising
    assert info["rest-stability_value"] < 0.01 * rest


def test_a_round_that_diverges_is_undone_and_the_start_kept(problem):
    # a step size no orbit survives (the rounds' Adam steps, none by default): the first
    # round's loss is not finite
    before, k, failed, info, _ = _enforced(problem, -50.0, learning_rate=1e6,
                                        constraint_adam_steps=50)
    assert before[0] > 100 * EnergyRising(1.0).tolerance
    assert not failed                            # the start is not lost
    assert k == -50.0                            # the model from before the round
    assert info["constraint_rounds"] == 0 and not info["constraints_met"]
    assert info["constraint_stop"].startswith("round 1 undone (constraints, round 1: loss is")
    assert info["energy-rising_value"] == pytest.approx(before[0])
    assert info["energy-rising_weight"] == 0.0       # the weights the kept model trained with


@pytest.mark.parametrize("fields, message", [
    (dict(system="oscillator"), "applies to --system flutter only"),
    (dict(system="flutter", training="trajectory"), "applies to --training periodic only"),
    (dict(system="flutter", starts_together=True), "one at a time"),
    (dict(system="flutter", approximator="gp"), "apply to --approximator nn only"),
])
def test_options_refuse_what_the_rounds_cannot_do(fields, message):
    with pytest.raises(ValueError, match=message):
        FitOptions(train=TrainConfig(constraint_rounds=2), **fields)


def test_rounds_must_be_a_count():
    with pytest.raises(ValueError, match="constraint_rounds must be an integer at least 0"):
        TrainConfig(constraint_rounds=-1)


def test_the_report_says_what_the_rounds_cost():
    held = {"start": 3, "info": {
        "constraint_rounds": 5, "constraints_met": True,
        "constraints_broken_before": ["rest-stability"],
        "misfit_before_rounds": 6.0e-5, "misfit_after_rounds": 9.0e-5,
        "energy-rising_weight": 0.0, "rest-stability_weight": 3.26e4}}
    untouched = {"start": 1, "info": {"constraint_rounds": 0, "constraints_met": True}}
    older = {"start": 4, "info": {"constraint_rounds": 2, "constraints_met": False,
                                  "rest-stability_weight": 10.0}}
    text = "\n".join(_constraint_rounds([untouched, held, older]))
    assert ("- start 3: broke `--rest-stability`; 5 round(s), final weights "
            "`--rest-stability` 3.26e+04, all met; the data's misfit 6e-05 → 9e-05 "
            "(+50%).") in text
    # a file written before the misfit was recorded: the rounds alone
    assert ("- start 4: broke a condition; 2 round(s), final weights `--rest-stability` 10, "
            "not all met.") in text
    assert "start 1" not in text
    assert _constraint_rounds([untouched]) == []
