"""Errors in the measured airspeeds (``--parameter-errors``, training.parameter_errors): every
orbit's parameter an unknown of the periodic stage with a prior whose scales are the data's
own scatter. Checked against points built on exact quadratics, against the rig's own orbits
logged at wrong airspeeds (the offsets found are the errors put in), and against the
option's checks."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tests.ude_fixtures import write_truth_campaign
from ude_fit import UDE, identify, load, training_data
from ude_fit.data.orbit import Orbit, OrbitDataset
from ude_fit.training.identify import ParameterErrors
from ude_fit.training.losses import orbit_unknowns, periodic_objective
from ude_fit.training.optimise import minimize
from ude_fit.training.options import FitOptions, TrainConfig
from ude_fit.data.estimates import data_scatter, parameter_scatter
from ude_fit.training.parameter_errors import parameter_errors

jax.config.update("jax_enable_x64", True)

pytestmark = pytest.mark.minutes(2.5)   # CI order: tests/conftest.py

CFG = TrainConfig().for_system("flutter")
AIRSPEEDS = (19.0, 21.0, 23.0, 25.0)
# the airspeeds the campaign below is logged at, off the true ones by these (m/s)
ERRORS = np.array([0.3, -0.25, 0.2, -0.3, 0.25, -0.2, 0.15, -0.15, 0.1, -0.1])


@pytest.fixture(scope="module")
def truth(tmp_path_factory):
    path = tmp_path_factory.mktemp("perr") / "f.h5"
    write_truth_campaign(path, "flutter", airspeeds=AIRSPEEDS)
    ds = load([path], "flutter")
    mech, _ = identify(training_data(ds), "flutter")
    return ds, mech


def _logged_at(ds: OrbitDataset, errors) -> OrbitDataset:
    orbits = tuple(dataclasses.replace(o, parameter=o.parameter + float(e))
                   for o, e in zip(ds.orbits, errors))
    return OrbitDataset(ds.system, orbits, ds.sources)


def _on_quadratics(errors) -> OrbitDataset:
    """Four stable and five unstable points whose airspeeds lie on a quadratic in the
    amplitude per class, moved by ``errors`` (one per point)."""
    amps = np.array([0.05, 0.06, 0.07, 0.08, 0.005, 0.01, 0.015, 0.02, 0.025])
    stable = [True] * 4 + [False] * 5
    V = np.where(stable, 20.0 + 300.0 * (amps - 0.04) ** 2, 26.0 - 9000.0 * amps ** 2)
    coeffs = lambda a: np.zeros((2, 15)) + np.eye(2, 15, 1) * a
    orbits = tuple(dataclasses.replace(
        _orbit_template(), parameter=float(v + e), coeffs=coeffs(a), stable=s)
        for v, e, a, s in zip(V, errors, amps, stable))
    return OrbitDataset("flutter", orbits, tuple(f"p{k}" for k in range(len(orbits))))


def _orbit_template():
    return Orbit(parameter=0.0, frequency=5.0, stable=None, coeffs=np.zeros((2, 15)),
                 forcing=None, noise=np.full(2, np.nan), periods=np.nan, source="synthetic")


def test_the_parameter_scatter_is_the_residual_about_each_class_quadratic():
    exact = _on_quadratics(np.zeros(9))
    assert parameter_scatter(exact) == pytest.approx(0.0, abs=1e-9)
    # errors with no component along 1, A, A^2 of their class: they are the residuals
    amps = exact.amplitudes()
    e = np.zeros(9)
    for cls in (slice(0, 4), slice(4, 9)):
        basis = np.vander(amps[cls], 3)
        r = np.random.default_rng(0).normal(size=basis.shape[0])
        e[cls] = r - basis @ np.linalg.lstsq(basis, r, rcond=None)[0]
    dof = (4 - 3) + (5 - 3)
    assert parameter_scatter(_on_quadratics(e)) == pytest.approx(
        np.sqrt(np.sum(e ** 2) / dof), rel=1e-9)
    # a class of three points says nothing
    three = OrbitDataset("flutter", exact.orbits[:3], exact.sources[:3])
    assert parameter_scatter(three) == 0.0


def test_a_one_sigma_offset_costs_what_a_one_sigma_amplitude_miss_does(truth):
    ds, _ = truth
    logged = _logged_at(ds, ERRORS[:len(ds)])
    data = training_data(logged)
    errors = parameter_errors(data, logged)
    assert np.allclose(errors.sigma, parameter_scatter(logged))
    # the misfit of orbit k, every state scaled by (1 + the amplitude scatter over its
    # amplitude), is the periodic objective's fit term of that scaled orbit
    amp = logged.amplitudes()
    rel = data_scatter(logged) * amp.max() / amp
    ys, scale = np.asarray(data.ys), np.asarray(data.y_scale)
    for k in range(len(logged)):
        scaled = ys[k] * (1 + rel[k])
        assert errors.cost[k] == pytest.approx(np.mean(((scaled - ys[k]) / scale) ** 2),
                                               rel=1e-12)


def _with_errors(data, ds, sigma, cost_factor=1.0):
    cost = cost_factor * parameter_errors(data, ds).cost
    return dataclasses.replace(data, param_errors=ParameterErrors(
        jnp.full(len(ds), sigma), cost))


def test_an_offset_puts_the_orbit_back_at_its_true_airspeed(truth):
    # the rig's orbits logged off their airspeeds: with every orbit moved back by its
    # error, the objective is the one of the orbits logged right, plus the prior's cost
    ds, mech = truth
    e = ERRORS[:len(ds)]
    sigma = 0.2
    logged = _with_errors(training_data(_logged_at(ds, e)), ds, sigma)
    right = training_data(ds)
    k1, k2 = jax.random.split(jax.random.PRNGKey(0))
    params = {"dy0": 1e-2 * jax.random.normal(k1, right.ys[:, 0, :].shape),
              "dT": 1e-3 * jax.random.normal(k2, right.period.shape)}
    u = -e / sigma
    back = float(periodic_objective(UDE(mech), {**params, "dP": jnp.asarray(u)}, logged, CFG))
    exact = float(periodic_objective(UDE(mech), params, right, CFG))
    prior = float(np.mean(np.asarray(logged.param_errors.cost) * u ** 2))
    assert back == pytest.approx(exact + prior, rel=1e-12)
    # at zero offsets the objective is the one of the log as it stands, prior-free
    as_logged = dataclasses.replace(logged, param_errors=None)
    assert float(periodic_objective(UDE(mech), {**params, "dP": jnp.zeros(len(ds))}, logged,
                                    CFG)) == float(periodic_objective(UDE(mech), params,
                                                                      as_logged, CFG))


def test_the_fit_moves_each_orbit_by_its_logging_error(truth):
    # the rig's orbits fitted with its identified model twice: as logged at their true
    # airspeeds and as logged off them by ERRORS. The offsets themselves also absorb the
    # identified model's own error (run on, by 0.9 m/s and more here: the model lacks the
    # wake's lag), which both fits share; their difference is each orbit's logging error,
    # moved back. (The twentieth of the prior's scale that an earlier test asked of the
    # offsets alone held only for an optimiser 300 steps short of the minimum.)
    ds, mech = truth
    sigma = 0.2
    e = ERRORS[:len(ds)]
    loss = lambda p, model, d: periodic_objective(model, p, d, CFG)
    found = []
    for data in (_with_errors(training_data(ds), ds, sigma),
                 _with_errors(training_data(_logged_at(ds, e)), ds, sigma)):
        params = orbit_unknowns(data, autonomous=True)
        assert set(params) == {"dy0", "dT", "dP"}
        params, _ = minimize(loss, params, (UDE(mech), data), adam_steps=0, lbfgs_steps=4000,
                             lr=1e-3)
        found.append(sigma * np.asarray(params["dP"]))
    moved = found[1] - found[0]
    assert np.all(np.sign(moved) == -np.sign(e)), moved
    # each error at least half recovered, and most of the errors' RMS (measured at 4000
    # steps: 0.28 of the worst error and 0.18 of the RMS left over; at 2000 steps one
    # machine's rounding left 0.48 and 0.31, short of the minimum, another's 0.41 and 0.18)
    assert np.all(np.abs(moved + e) < 0.5 * np.abs(e)), moved
    assert np.sqrt(np.mean((moved + e) ** 2)) < 0.3 * np.sqrt(np.mean(e ** 2)), moved


def test_a_stage_keeps_the_errors_of_its_orbits(truth):
    ds, _ = truth
    data = training_data(ds)
    data = dataclasses.replace(data, param_errors=parameter_errors(data, ds))
    mask = np.arange(len(ds)) % 2 == 1
    stage = data.only(mask)
    idx = np.where(mask, np.arange(len(ds)), np.flatnonzero(mask)[0])
    assert np.array_equal(stage.param_errors.cost, data.param_errors.cost[idx])


@pytest.mark.parametrize("fields, message", [
    (dict(system="oscillator"), "applies to --system flutter with --training periodic"),
    (dict(system="flutter", training="trajectory"),
     "applies to --system flutter with --training periodic"),
    (dict(system="flutter", approximator="gp"), "apply to --approximator nn only"),
])
def test_the_option_is_refused_where_it_does_not_apply(fields, message):
    with pytest.raises(ValueError, match=message):
        FitOptions(**fields, train=TrainConfig(parameter_errors=True))
    with pytest.raises(ValueError, match="parameter_errors must be True or False"):
        TrainConfig(parameter_errors=1)
