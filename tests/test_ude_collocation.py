"""The periodic objective by collocation (ude_fit.training.collocation) against shooting's
(ude_fit.training.losses.orbit_terms) on the aerofoil model's own limit cycles, its monodromy
matrix against a linear system's exact one, and the hand-over to shooting."""
from __future__ import annotations

import jax  # noqa: E402
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.linalg import expm

from ude_fit.models.flow import ordered_product, rk4_orbit, rk4_orbit_monodromy
from ude_fit.models.mechanistic import Drive
from ude_fit.training import collocation
from ude_fit.training.collocation import (Basis, collocation_terms, collocation_unknowns,
                                          harmonics_of, monodromy, shooting_unknowns)
from ude_fit.training.identify import TrainingData
from ude_fit.training.losses import orbit_terms, orbit_unknowns
from ude_fit.training.options import TrainConfig
from tests.model_orbits import traced_orbits

jax.config.update("jax_enable_x64", True)

SAMPLES, SUBSTEPS = 32, 8         # the fits' samples per period; a fine exact orbit


@pytest.fixture(scope="module")
def traced():
    """Three orbits, one unstable and two stable (the largest traced among them)."""
    def picks(branch):
        unstable, stable = np.flatnonzero(~branch.stable), np.flatnonzero(branch.stable)
        return unstable[len(unstable) // 2], stable[len(stable) // 3], stable[-1]
    return traced_orbits(SAMPLES, SUBSTEPS, picks)


def test_an_exact_orbit_collocates_with_shootings_stability(traced):
    model, data, label = traced
    cfg = TrainConfig(substeps=SUBSTEPS).for_system("flutter")
    shot = orbit_terms(model, orbit_unknowns(data, True), data, cfg)
    col = collocation_terms(model, collocation_unknowns(data, True), data, cfg)
    # the measured samples are the series' samples, and the series is the model's orbit
    assert np.all(np.asarray(col.fit) < 1e-12)
    assert np.all(np.asarray(col.closure) < 1e-6)
    # the same stability, by the variational equation along the series at one Runge-Kutta
    # step per sample (shooting takes eight here): the fold test's sign everywhere, its
    # value and the other two tests' within 1 %
    assert np.all(np.sign(np.asarray(col.indicator)) == label)
    np.testing.assert_allclose(np.asarray(col.indicator), np.asarray(shot.indicator),
                               rtol=1e-2)
    stable = label > 0
    np.testing.assert_allclose(np.asarray(col.secondary)[stable],
                               np.asarray(shot.secondary)[stable], rtol=1e-2)


def test_an_orbit_off_the_model_has_a_defect(traced):
    """The defect measures how far the series is from being the model's orbit: the same
    orbits at another airspeed are not the model's orbits there."""
    model, data, _ = traced
    cfg = TrainConfig().for_system("flutter")
    moved = TrainingData(data.ys, data.qdd, data.period,
                       Drive(data.drive.param + 2.0, data.drive.omega, data.drive.fc),
                       data.label, data.y_scale, data.amp_max)
    col = collocation_terms(model, collocation_unknowns(moved, True), moved, cfg)
    assert np.all(np.asarray(col.closure) > 1e-4)


def test_the_monodromy_matrix_converges_at_fourth_order():
    """A constant linear system's monodromy is exp(J T); the Runge-Kutta product's error
    falls sixteen-fold when the step halves (classical RK4)."""
    rng = np.random.default_rng(3)
    J = rng.normal(size=(4, 4))
    J = J - (np.max(np.real(np.linalg.eigvals(J))) + 0.3) * np.eye(4)   # decaying
    T = 2 * np.pi / np.max(np.abs(np.imag(np.linalg.eigvals(J))) + 1.0)
    exact = expm(J * T)
    errors = []
    for m in (32, 64, 128):
        M = monodromy(jnp.asarray(np.broadcast_to(J, (m, 4, 4))), T)
        errors.append(np.max(np.abs(np.asarray(M) - exact)))
    assert errors[-1] < 1e-6 * np.max(np.abs(exact))
    for coarse, fine in zip(errors, errors[1:]):
        assert 12 < coarse / fine < 20


def test_an_odd_number_of_steps_multiplies_in_order():
    rng = np.random.default_rng(1)
    P = rng.normal(size=(7, 3, 3))
    want = np.eye(3)
    for p in P:
        want = p @ want
    np.testing.assert_allclose(np.asarray(ordered_product(jnp.asarray(P))),
                               want, rtol=1e-12, atol=1e-12)


def test_shooting_starts_where_the_series_does(traced):
    _, data, _ = traced
    zero = collocation_unknowns(data, True)
    # (all but the samples' Nyquist component, which the series leaves out)
    assert np.max(np.abs(np.asarray(shooting_unknowns(zero, data)["dy0"]))) < 1e-6
    rng = np.random.default_rng(0)
    moved = {**zero, "dC": jnp.asarray(rng.normal(size=zero["dC"].shape) * 0.01),
             "dT": jnp.asarray([0.01, -0.02, 0.0])}
    basis = Basis.of(SAMPLES)
    C = np.asarray(collocation._orbit_series(basis, data, moved["dC"]))
    at_zero = np.asarray(basis.samples)[0] @ C                  # (orbits, states)
    got = shooting_unknowns(moved, data)
    np.testing.assert_allclose(np.asarray(got["dy0"]),
                               (at_zero - np.asarray(data.ys[:, 0])) / np.asarray(data.y_scale),
                               rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(np.asarray(got["dT"]), np.asarray(moved["dT"]))
    assert harmonics_of(SAMPLES) == 15


def test_the_stagewise_monodromy_is_the_flows_derivative(traced):
    """Shooting's monodromy matrix from the Jacobians at every Runge-Kutta stage is the
    derivative of the discrete flow in its start state, as forward-mode autodiff through
    the integration gives it; here with an imposed force periodic in the orbit's period, so
    the stages' times matter too."""
    model, data, _ = traced
    fc = np.zeros(15)
    fc[[1, 9]] = (3.0, -1.5)                     # a1 cos + b2 sin, in N on heave
    for k in range(data.n_orbits):
        T = data.period[k]
        drive = Drive.of(data.drive.param[k], 2 * np.pi / T, fc)
        y0 = data.ys[k, 0]

        def flow(y):
            yT, ys = rk4_orbit(model, y, T, drive, 96)
            return yT, (yT, ys)
        want, (yT, ys) = jax.jacfwd(flow, has_aux=True)(y0)
        got_yT, got_ys, got = rk4_orbit_monodromy(model, y0, T, drive, 96)
        np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=1e-12,
                                   atol=1e-12 * float(jnp.max(jnp.abs(want))))
        np.testing.assert_allclose(np.asarray(got_yT), np.asarray(yT), rtol=1e-13)
        np.testing.assert_allclose(np.asarray(got_ys), np.asarray(ys), rtol=1e-13,
                                   atol=1e-15)
