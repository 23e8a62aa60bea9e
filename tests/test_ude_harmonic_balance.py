"""The one-harmonic balance followed in amplitude (ude_fit/models/harmonic_balance.py)
against known truth: systems whose limit cycles are exact circles of known radius (so the
one-harmonic ansatz is exact, the mean included), sub- and supercritical; and on the
aerofoil, the unstable-branch condition it serves (training/penalties.py) against the
model's own first Lyapunov coefficient."""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest

from tests.test_ude_criticality import MIX, Circles
from tests.ude_fixtures import write_truth_campaign
from ude_fit import UDE, identify, load, training_data
from ude_fit.analysis.criticality import hopf_criticality
from ude_fit.models import harmonic_balance
from ude_fit.training.options import FitOptions, TrainConfig
from ude_fit.training.penalties import (UnstableBranch, constraints_for, regularity_points,
                                        unstable_band)
from ude_fit.training.rounds import enforce_constraints

import jax  # noqa: E402  (after the imports above, before any array)

jax.config.update("jax_enable_x64", True)

pytestmark = pytest.mark.minutes(3)   # CI order: tests/conftest.py


def _circle_guess(system: Circles, a: float, V: float):
    """Unknowns near the orbit of heave amplitude ``a``: the circle's first harmonic through
    MIX, a frequency and an airspeed a little off (Newton has to move them)."""
    h = MIX[:, 0] - 1j * MIX[:, 1]               # x = Re(h r e^{i omega t}), u1 = r cos
    h = h * np.exp(-1j * np.angle(h[0])) * (a / abs(h[0]))
    return jnp.asarray(np.concatenate([np.zeros(4), h.real[1:], -h.imag[1:],
                                       [1.02 * system.omega, V]]))


@pytest.mark.parametrize("a, gamma", [(1.5, 0.8), (1.5, -8.0), (-1.0, 0.0)])
def test_the_branch_of_exact_circles(a, gamma):
    system = Circles(a=jnp.asarray(a), gamma=jnp.asarray(gamma))
    slope = system.amplitude2_slope()                 # dA²/dV, exact
    amps = jnp.linspace(0.01, 0.3, 12)
    zs, ok = harmonic_balance.follow(system, amps, _circle_guess(system, 0.01, 20.0 + 1e-4 /
                                                                 slope), jnp.ones(4))
    assert np.all(np.asarray(ok))
    V = np.asarray(zs[:, -1])
    np.testing.assert_allclose(V, system.V0 + np.asarray(amps) ** 2 / slope, rtol=1e-10)
    np.testing.assert_allclose(np.asarray(zs[:, -2]), system.omega, rtol=1e-10)
    # the mean the feedback state w holds on every orbit (kappa r² / lam), through MIX
    r2 = (np.asarray(amps) / np.hypot(MIX[0, 0], MIX[0, 1])) ** 2
    np.testing.assert_allclose(np.asarray(zs[:, :4]), np.outer(r2 * system.kappa / system.lam,
                                                               MIX[:, 2]), atol=1e-12)
    dV_da = harmonic_balance.airspeed_slopes(system, zs, amps, jnp.ones(4))
    np.testing.assert_allclose(np.asarray(dV_da), 2 * np.asarray(amps) / slope, rtol=1e-8)


def test_a_point_it_cannot_reach_is_reported_not_guessed():
    # supercritical circles exist only above V0; asked for amplitudes from a guess with
    # a frequency far off every orbit, Newton's first solve fails and nothing converges
    system = Circles(a=jnp.asarray(-1.0), gamma=jnp.asarray(0.0))
    guess = _circle_guess(system, 0.01, 20.0).at[-2].set(1e-3)
    zs, ok = harmonic_balance.follow(system, jnp.linspace(0.01, 0.3, 6), guess, jnp.ones(4),
                                     first_steps=2, steps=2)
    assert not np.any(np.asarray(ok))
    assert np.all(np.isfinite(np.asarray(zs)))         # what stands in is finite


def test_the_branch_starts_at_the_hopf_point():
    # subcritical circles: the Hopf point V0 with the linear frequency, from a grid of
    # airspeeds; followed from there, the branch of exact circles
    system = Circles(a=jnp.asarray(1.5), gamma=jnp.asarray(0.8))
    amps = jnp.linspace(0.005, 0.3, 8)
    z0 = harmonic_balance.hopf_start(system, jnp.linspace(15.0, 25.0, 11), amps[0])
    assert float(z0[-1]) == pytest.approx(system.V0, abs=1e-9)
    assert float(z0[-2]) == pytest.approx(system.omega, rel=1e-12)
    zs, ok = harmonic_balance.follow(system, amps, z0, jnp.ones(4))
    assert np.all(np.asarray(ok))
    np.testing.assert_allclose(np.asarray(zs[:, -1]), system.V0 + np.asarray(amps) ** 2
                               / system.amplitude2_slope(), rtol=1e-10)


def test_the_unstable_band_is_read_from_the_data():
    # lee2020/model2's shape: unstable orbits growing as the airspeed falls up to the fourth
    # in amplitude, then scattered; stable ones above
    P = np.array([25.8, 25.0, 24.1, 21.6, 22.4, 20.6, 23.3, 20.7, 21.5])
    amp = np.array([7.4, 13.3, 17.9, 24.7, 29.4, 29.9, 30.6, 51.5, 63.1]) * 1e-3
    lab = np.array([-1] * 7 + [1] * 2)
    amps = unstable_band(P, amp, lab)
    assert amps[0] == pytest.approx(0.05 * 7.4e-3) and amps[-1] == pytest.approx(24.7e-3)
    assert np.all(np.diff(amps) > 0)
    # a stable orbit between two unstable ones in amplitude ends the stretch
    amp2 = amp.copy()
    amp2[7] = 15e-3
    assert unstable_band(P, amp2, lab)[-1] == pytest.approx(13.3e-3)
    amp2[7] = 10e-3                      # the smallest orbit alone: from rest up to it
    assert unstable_band(P, amp2, lab)[-1] == pytest.approx(7.4e-3)
    # a stable orbit smaller than every unstable one: the branch from the Hopf point is a
    # stable one, and the data shows no unstable stretch from it
    amp2[8] = 5e-3
    assert unstable_band(P, amp2, lab) is None
    assert unstable_band(P, amp, np.ones(9)) is None


class CubicHeaveDamping(eqx.Module):
    """A heave force −k 1e3 h'³: energy taken out as the swing grows, so a large enough k
    turns the aerofoil's subcritical Hopf point supercritical."""
    k: jax.Array

    def __call__(self, z):
        return jnp.stack([-self.k * 1e3 * z[2] ** 3, 0.0 * z[4]])


@pytest.fixture(scope="module")
def aerofoil(tmp_path_factory):
    path = tmp_path_factory.mktemp("unstable_branch") / "f.h5"
    write_truth_campaign(path, "flutter", airspeeds=(18.0, 21.0, 23.6))
    data = training_data(load([path], "flutter"))
    mech, _ = identify(data, "flutter")
    return data, mech, regularity_points(data)


def test_the_unstable_branch_condition_against_the_criticality(aerofoil):
    data, mech, reg = aerofoil
    cond = UnstableBranch(1.0)
    value = eqx.filter_jit(lambda m: cond.value(m, reg))
    # the mechanistic model identified from the rig's orbits: a subcritical Hopf point and
    # a branch whose airspeed falls all the way up to the largest unstable orbit (18 m/s)
    for k, subcritical in ((0.0, True), (0.3, False), (1.0, False)):
        model = UDE(mech, CubicHeaveDamping(jnp.asarray(k)))
        crit = hopf_criticality(model, (15.0, 30.0))
        assert crit.subcritical is subcritical
        v = float(value(model))
        assert (v <= cond.tolerance) is subcritical, (k, v)
    # the branch the condition reads starts at the model's own Hopf point
    model = UDE(mech, CubicHeaveDamping(jnp.asarray(0.0)))
    z0 = harmonic_balance.hopf_start(model, reg.V, reg.band_amp[0])
    zs, ok = harmonic_balance.follow(model, reg.band_amp, z0, reg.y_scale)
    assert np.all(np.asarray(ok))
    assert float(zs[0, -1]) == pytest.approx(hopf_criticality(model, (15.0, 30.0)).param,
                                             abs=0.01)
    assert np.all(np.diff(np.asarray(zs[:, -1])) < 0)


def test_the_constraint_rounds_hold_the_unstable_branch_when_asked(aerofoil):
    # a trainable cubic damping that makes the Hopf point supercritical (k = 1, above): the
    # rounds weigh the broken condition from the data's misfit and train until the branch
    # leaves its Hopf point subcritically again, as the model's own criticality says
    data, mech, reg = aerofoil
    cfg = TrainConfig(adam_steps=50, lbfgs_steps=20, constraint_rounds=3,
                      constrain_unstable_branch=True).for_system("flutter")
    assert [c.option for c in constraints_for(cfg)] == ["energy-rising", "rest-stability",
                                                         "unstable-branch"]
    assert [c.option for c in constraints_for(dataclasses.replace(
        cfg, constrain_unstable_branch=False))] == ["energy-rising", "rest-stability"]
    trainable, static = eqx.partition(CubicHeaveDamping(jnp.asarray(1.0)), eqx.is_inexact_array)
    params = {"corr": trainable, "dy0": jnp.zeros(data.ys[:, 0, :].shape),
              "dT": jnp.zeros(data.period.shape)}
    out, _, failed, info = enforce_constraints(params, static, mech, data, cfg, reg,
                                               np.array([np.nan]))
    assert not failed
    assert info["constraint_rounds"] >= 1 and info["unstable-branch_weight"] > 0
    assert info["unstable-branch_value"] <= UnstableBranch(1.0).tolerance
    k = float(out["corr"].k)
    assert k < 1.0
    assert hopf_criticality(UDE(mech, CubicHeaveDamping(jnp.asarray(k))),
                            (15.0, 30.0)).subcritical


def test_the_condition_needs_the_constraint_rounds():
    with pytest.raises(ValueError, match="--constrain-unstable-branch needs the constraint "
                       "rounds"):
        FitOptions(system="flutter", train=TrainConfig(constraint_rounds=0,
                                                       constrain_unstable_branch=True))
    with pytest.raises(ValueError, match="--constrain-unstable-branch needs"):
        FitOptions(system="flutter", training="trajectory",
                   train=TrainConfig(constrain_unstable_branch=True))
    with pytest.raises(ValueError, match="constrain_unstable_branch must be True or False"):
        TrainConfig(constrain_unstable_branch=1)
    assert FitOptions(system="flutter", train=TrainConfig(
        constrain_unstable_branch=True)).train.for_system("flutter").constraint_rounds == 7
