"""The periodic objective by collocation (ude_fit.training.collocation) against shooting's
(ude_fit.training.losses.orbit_terms) on the aerofoil model's own limit cycles, its monodromy
matrix against a linear system's exact one, the orbits' series solved for the model
(ude_fit.training.projection) and its normal matrix against the dense product, and the
hand-over to shooting."""
from __future__ import annotations

import jax  # noqa: E402
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.linalg import expm

from ude_fit.models.flow import ordered_product, rk4_orbit, rk4_orbit_monodromy
from ude_fit.models.mechanistic import Drive
from ude_fit.training import projection
from ude_fit.training.collocation import (FREE_LEAD, PLANS, SERIES, FreeSeries,
                                          collocation_terms, collocation_unknowns, monodromy,
                                          orbit_series, plan_legs, shooting_unknowns)
from ude_fit.training.fourier import Basis, harmonics_of
from ude_fit.training.projection import OrbitResiduals
from ude_fit.training.identify import TrainingData
from ude_fit.training.losses import orbit_terms, orbit_unknowns
from ude_fit.training.options import TrainConfig
from tests.model_orbits import traced_orbits

jax.config.update("jax_enable_x64", True)

SAMPLES, SUBSTEPS = 32, 8         # the fits' samples per period; a fine exact orbit
FREE = TrainConfig(collocation_series="free").for_system("flutter")


@pytest.fixture(scope="module")
def traced():
    """Three orbits, one unstable and two stable (the largest traced among them)."""
    def picks(branch):
        unstable, stable = np.flatnonzero(~branch.stable), np.flatnonzero(branch.stable)
        return unstable[len(unstable) // 2], stable[len(stable) // 3], stable[-1]
    return traced_orbits(SAMPLES, SUBSTEPS, picks)


def test_an_exact_orbit_collocates_with_shootings_stability(traced):
    model, data, label = traced
    cfg = TrainConfig(substeps=SUBSTEPS, collocation_series="free").for_system("flutter")
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
    cfg = FREE
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
    model, data, _ = traced
    cfg = FREE
    zero = collocation_unknowns(data, True)
    # (all but the samples' Nyquist component, which the series leaves out)
    assert np.max(np.abs(np.asarray(shooting_unknowns(model, zero, data, cfg)["dy0"]))) < 1e-6
    rng = np.random.default_rng(0)
    moved = {**zero, "dC": jnp.asarray(rng.normal(size=zero["dC"].shape) * 0.01),
             "dT": jnp.asarray([0.01, -0.02, 0.0])}
    basis = Basis.of(SAMPLES)
    C = np.asarray(FreeSeries().series(model, moved, data, cfg))
    at_zero = np.asarray(basis.samples)[0] @ C                  # (orbits, states)
    got = shooting_unknowns(model, moved, data, cfg)
    np.testing.assert_allclose(np.asarray(got["dy0"]),
                               (at_zero - np.asarray(data.ys[:, 0])) / np.asarray(data.y_scale),
                               rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(np.asarray(got["dT"]), np.asarray(moved["dT"]))
    assert harmonics_of(SAMPLES) == 15


SOLVED = TrainConfig(collocation_series="solved").for_system("flutter")


def _moved(data, dv=2.0):
    """The same orbits at another airspeed: not the model's orbits there."""
    return TrainingData(data.ys, data.qdd, data.period,
                        Drive(data.drive.param + dv, data.drive.omega, data.drive.fc),
                        data.label, data.y_scale, data.amp_max)


def _orbit_objective(model, data, k, weight):
    """Orbit k's misfit plus ``weight`` times its defect, as a function of its series."""
    basis = Basis.of(SAMPLES)
    drive = jax.tree_util.tree_map(lambda x: x[k], data.drive)
    res = OrbitResiduals.of(model.at_drive(drive), drive, basis, data.ys[k], data.period[k],
                            jnp.ones(data.ys.shape[2]), data.y_scale)
    return res, lambda C: (jnp.sum(res.misfit(C) ** 2)
                           + weight * jnp.sum(res.defect(C, res.field(C)[1]) ** 2))


def test_the_normal_matrix_is_the_residuals_gram_matrix(traced):
    """The Gauss-Newton matrix and gradient formed from Fourier transforms of the field's
    Jacobians are the dense Jacobian's J^T J and J^T r (to rounding), here 2 m/s off the
    model's orbits where the defect is large."""
    model, data, _ = traced
    w = SOLVED.closure_weight
    moved = _moved(data)
    res, _ = _orbit_objective(model, moved, 0, w)
    C = Basis.of(SAMPLES).through(moved.ys[0])
    H, g = res.normal_equations(C, w)

    def residual(c):
        return jnp.concatenate([res.misfit(c).reshape(-1),
                                np.sqrt(w) * res.defect(c, res.field(c)[1]).reshape(-1)])
    A = jax.jacfwd(lambda c: residual(c.reshape(C.shape)))(C.reshape(-1))
    np.testing.assert_allclose(np.asarray(H), np.asarray(A.T @ A), rtol=1e-9,
                               atol=1e-12 * float(jnp.max(jnp.abs(H))))
    np.testing.assert_allclose(np.asarray(g), np.asarray(A.T @ residual(C)), rtol=1e-9,
                               atol=1e-12 * float(jnp.max(jnp.abs(g))))
    # the sum a step is judged against is the residuals' squared norm
    assert float(res.objective(C, w)) == pytest.approx(float(jnp.sum(residual(C) ** 2)),
                                                       rel=1e-12)


def test_a_step_is_the_longest_fraction_that_lowers_the_sum(traced):
    """A Gauss-Newton step takes the longest of its fractions that lowers the objective,
    else none, on orbits 2, 6 and 12 m/s off the model's, where the full step overshoots
    on some of them."""
    model, data, _ = traced
    w = SOLVED.closure_weight
    fractions = np.asarray(projection.BACKTRACK)
    taken = []
    for dv in (2.0, 6.0, 12.0):
        moved = _moved(data, dv)
        for k in range(moved.n_orbits):
            res, J = _orbit_objective(model, moved, k, w)
            C = Basis.of(SAMPLES).through(moved.ys[k])
            H, g = res.normal_equations(C, w)
            now = res.objective(C, w)
            step = np.linalg.solve(np.asarray(H), np.asarray(g)).reshape(C.shape)
            lower = [float(J(C - a * step)) < float(now) for a in fractions]
            taken.append(lower.index(True) if any(lower) else None)
            want = C - fractions[taken[-1]] * step if any(lower) else C
            np.testing.assert_allclose(np.asarray(res.gauss_newton_step(C, w)),
                                       np.asarray(want), rtol=1e-10, atol=1e-14)
    assert 0 in taken and any(t != 0 for t in taken), taken


def test_an_exact_orbit_is_its_own_solved_series(traced):
    model, data, label = traced
    terms = collocation_terms(model, collocation_unknowns(data, True, series="solved"), data,
                              SOLVED)
    assert np.all(np.asarray(terms.fit) < 1e-12)
    assert np.all(np.asarray(terms.closure) < 1e-6)
    assert np.all(np.sign(np.asarray(terms.indicator)) == label)


def test_the_series_are_solved_for_the_model(traced):
    """Each orbit's series is the minimum of its misfit plus the weighted defect for the
    model of the moment (variable projection): near the model's orbits (the same orbits
    0.5 m/s off) the objective's gradient in the series all but vanishes and more
    Gauss-Newton steps change the sum by under 1 %; 2 m/s off the steps are cut back but
    still lower it."""
    model, data, _ = traced
    w = SOLVED.closure_weight
    basis = Basis.of(SAMPLES)
    for dv, converged_to in ((0.5, 0.02), (2.0, None)):
        moved = _moved(data, dv)
        unknowns = collocation_unknowns(moved, True, series="solved")
        assert set(unknowns) == {"dT"}          # the series are not the optimiser's
        C = orbit_series(model, unknowns, moved, SOLVED)
        measured = basis.through(moved.ys)
        for k in range(moved.n_orbits):
            _, J = _orbit_objective(model, moved, k, w)
            assert float(J(C[k])) < 0.9 * float(J(measured[k]))
            if converged_to is not None:    # near the model's orbits: all but converged
                g0 = np.linalg.norm(np.asarray(jax.grad(J)(measured[k])))
                g = np.linalg.norm(np.asarray(jax.grad(J)(C[k])))
                assert g < converged_to * g0
    moved = _moved(data, 0.5)
    unknowns = collocation_unknowns(moved, True, series="solved")
    steps = projection.SERIES_STEPS
    try:
        projection.SERIES_STEPS = 8
        converged = collocation_terms(model, unknowns, moved, SOLVED)
    finally:
        projection.SERIES_STEPS = steps
    got = collocation_terms(model, unknowns, moved, SOLVED)
    total = np.asarray(got.fit + w * got.closure)
    want = np.asarray(converged.fit + w * converged.closure)
    assert np.all(total >= want * (1 - 1e-9))
    np.testing.assert_allclose(total, want, rtol=1e-2)


def test_the_objective_has_no_gradient_through_the_solve(traced):
    """The model's gradient is the objective's at fixed series (at the inner minimum the
    series' own change moves it by nothing to first order): a finite difference in the
    airspeed, series solved again each time, matches the derivative at fixed series."""
    model, data, _ = traced
    w = SOLVED.closure_weight

    def total(dv):
        moved = _moved(data, dv)
        t = collocation_terms(model, collocation_unknowns(moved, True, series="solved"),
                              moved, SOLVED)
        return jnp.sum(t.fit + w * t.closure)
    h = 1e-3
    fd = (float(total(0.5 + h)) - float(total(0.5 - h))) / (2 * h)
    np.testing.assert_allclose(float(jax.grad(total)(0.5)), fd, rtol=2e-2)


def test_shooting_starts_where_the_solved_series_does(traced):
    model, data, _ = traced
    moved_data = _moved(data)
    moved = {"dT": jnp.asarray([0.01, -0.02, 0.0])}
    C = np.asarray(orbit_series(model, moved, moved_data, SOLVED))
    at_zero = np.asarray(Basis.of(SAMPLES).samples)[0] @ C      # (orbits, states)
    got = shooting_unknowns(model, moved, moved_data, SOLVED)
    np.testing.assert_allclose(np.asarray(got["dy0"]),
                               (at_zero - np.asarray(data.ys[:, 0])) / np.asarray(data.y_scale),
                               rtol=1e-12, atol=1e-12)
    assert np.max(np.abs(np.asarray(got["dy0"]))) > 1e-4      # the series moved
    np.testing.assert_array_equal(np.asarray(got["dT"]), np.asarray(moved["dT"]))


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


def test_a_plans_legs_share_the_first_trainings_steps():
    assert plan_legs("free", 3000, 600) == [("free", 3000, 600)]
    assert plan_legs("solved", 3000, 600) == [("solved", 3000, 600)]
    legs = plan_legs("free-then-solved", 3000, 600)
    assert [leg[0] for leg in legs] == ["free", "solved"]
    assert legs[0][1] == round(FREE_LEAD * 3000) and legs[0][2] == 0
    assert legs[0][1] + legs[1][1] == 3000 and legs[1][2] == 600
    for steps in (0, 1, 7, 25):            # the legs' Adam steps add up to the training's
        assert sum(adam for _, adam, _ in plan_legs("free-then-solved", steps, 5)) == steps
    # every plan ends where its objective is evaluated: the series a plan ends with
    for plan in PLANS:
        assert PLANS[plan][-1].series in SERIES
        assert TrainConfig(collocation_series=plan).collocation_series == plan
