"""The amplitude form of the correction (ude_fit.models.amplitude, ``--correction-form
amplitude``): linear terms plus a damping convex in the orbit's size. Checked against what the
form promises by construction: the linearisation at rest is the explicit linear terms, the
damping coefficient is convex and vanishes at rest, the damping force never feeds energy in
where its coefficient is positive, the pinned Hopf point is where the continuation finds it
and stays there when the linear terms change. (At most one fold is *not* promised: a random
correction traced on the nominal aerofoil had four; docs/experiments.md, twelfth session.)"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ude_fit.analysis.continuation import hopf_point
from ude_fit.model_file import load_model, save_model
from ude_fit.models.amplitude import AmplitudeCorrection, SizeBasis, pin_hopf, resolve
from ude_fit.models.corrections import Scaling
from ude_fit.models.mechanistic import Drive, FlutterQS
from ude_fit.models.ude import UDE
from ude_fit.training.options import FitOptions, TrainConfig

jax.config.update("jax_enable_x64", True)

# state spreads of the aerofoil's orbits (m, rad, m/s, rad/s; velocities = 2 pi 2.4 Hz times
# the displacements), airspeed mean and spread, force RMS (N, N m)
SCALING = Scaling(jnp.array([0.0, 0.0, 0.0, 0.0, 22.0]),
                  jnp.array([0.03, 0.05, 0.45, 0.75, 2.0]), jnp.array([20.0, 1.0]))
SCALES = np.array([0.03, 0.05, 0.45, 0.75])


def _correction(key=0, size=1.0, linear=0.0):
    """Random weights of scale ``size``; linear terms of scale ``linear``."""
    c = AmplitudeCorrection(2, SCALING, SizeBasis.spanning(np.array([0.0, 2.0]), 6),
                            key=jax.random.PRNGKey(key), init_scale=size)
    L = linear * jax.random.normal(jax.random.PRNGKey(100 + key), (2, 4))
    return eqx.tree_at(lambda m: (m.rest.matrices, m.linear), c, (L, jnp.zeros_like(L)))


def test_value_and_slope_at_rest_are_the_linear_terms_alone():
    c = _correction(size=3.0, linear=0.5)
    c = eqx.tree_at(lambda m: m.linear, c, 0.3 * jnp.ones((2, 4)))     # a trained change
    # by hand: out_scale_i (fixed + trained)_ij / y_scale_j, force per state unit
    want = (np.asarray(SCALING.out_scale)[:, None] * (np.asarray(c.rest.matrices) + 0.3)
            / np.asarray(SCALING.z_scale[:4])[None, :])
    for V in (15.0, 22.0, 28.0):
        assert np.allclose(c(jnp.array([0.0, 0.0, 0.0, 0.0, V])), 0.0, atol=1e-12)
        J = jax.jacfwd(lambda y: c(jnp.concatenate([y, jnp.array([V])])))(jnp.zeros(4))
        assert np.allclose(J, want, atol=1e-9)
    assert np.allclose(c.linear_matrix(), want, atol=1e-12)


@pytest.mark.parametrize("key", [0, 1, 2])
def test_the_damping_coefficient_is_convex_and_zero_at_rest(key):
    c = _correction(key, size=3.0)
    e = np.linspace(0.0, 3.0, 301)
    phi = np.array([float(c.phi(x)) for x in e])
    assert phi[0] == pytest.approx(0.0, abs=1e-12)
    assert np.min(np.diff(phi, 2)) > -1e-10
    # not a straight line: the ramps bend it (so convexity is a property, not a given)
    assert np.max(np.diff(phi, 2)) > 1e-8


def test_the_damping_force_does_no_positive_work_where_its_coefficient_is_positive():
    c = _correction(3, size=2.0)        # no linear terms: the damping alone
    rng = np.random.default_rng(0)
    for _ in range(50):
        y = rng.normal(size=4) * SCALES
        U = np.asarray(c(jnp.concatenate([jnp.asarray(y), jnp.array([22.0])])))
        e = float(c.size(jnp.asarray(y) / SCALING.z_scale[:4]))
        power = float(U @ y[2:])
        assert power * np.sign(float(c.phi(e))) <= 1e-12


@pytest.mark.parametrize("v_hopf", [21.0, 27.5])
def test_pinning_puts_the_hopf_point_where_asked(v_hopf):
    """pin_hopf's one damping moves the equilibrium's loss of stability to the airspeed the
    data's unstable orbits point at, as the continuation's own Hopf search finds it."""
    model = UDE(FlutterQS.nominal(), _correction(5, size=0.5))
    before = hopf_point(model, (10.0, 40.0))["param"]
    pinned = pin_hopf(model, v_hopf)
    assert abs(before - v_hopf) > 0.5                      # the test moves it
    assert hopf_point(pinned, (10.0, 40.0))["param"] == pytest.approx(v_hopf, abs=1e-6)
    # only the linear terms changed: the damping on each velocity, in scaled units
    L = np.asarray(pinned.correction.rest.matrices)
    assert np.allclose(L[:, :2], 0.0)
    assert L[0, 2] == pytest.approx(L[1, 3]) and L[0, 3] == L[1, 2] == 0.0


def test_a_trained_change_of_the_linear_terms_keeps_the_held_hopf_point():
    """resolve adds the one damping that holds the Hopf point where pin_hopf put it, whatever
    the trained change of the linear terms (here random: damping, stiffness, couplings)."""
    pinned = pin_hopf(UDE(FlutterQS.nominal(), _correction(6, size=0.5)), 26.0)
    change = 0.05 * jax.random.normal(jax.random.PRNGKey(7), (2, 4))
    moved = eqx.tree_at(lambda m: m.correction.linear, pinned, change)
    unheld = moved.with_correction(eqx.tree_at(lambda c: c.rest, moved.correction,
                                               type(moved.correction.rest)(
                                                   moved.correction.rest.matrices)))
    free = hopf_point(resolve(unheld), (10.0, 40.0))
    assert free is None or abs(free["param"] - 26.0) > 0.2      # the change moves it
    held = resolve(moved)
    assert held.correction.rest.v_hopf is None                  # concrete: nothing left to solve
    assert hopf_point(held, (10.0, 40.0))["param"] == pytest.approx(26.0, abs=1e-6)


def test_model_file_round_trip(tmp_path):
    model = UDE(FlutterQS.nominal(), _correction(4, size=1.0, linear=0.1))
    save_model(tmp_path / "m.eqx", model)
    back, header = load_model(tmp_path / "m.eqx")
    assert header["correction"]["kind"] == "amplitude"
    y = jnp.array([0.02, 0.03, 0.3, 0.5])
    d = Drive.of(22.0)
    assert np.allclose(back.vector_field(0.0, y, d), model.vector_field(0.0, y, d))


def test_the_form_is_for_the_aerofoils_correction():
    with pytest.raises(ValueError, match="--correction-form amplitude applies to --system "
                                         "flutter"):
        FitOptions(system="oscillator", train=TrainConfig(form="amplitude"))
    with pytest.raises(ValueError, match="--correction-form amplitude"):
        FitOptions(system="flutter", approximator="gp", train=TrainConfig(form="amplitude"))
    with pytest.raises(ValueError, match="not with --rest-free"):
        TrainConfig(form="amplitude", rest_free=True)
    with pytest.raises(ValueError, match="form must be"):
        TrainConfig(form="spline")
