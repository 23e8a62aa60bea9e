"""The rest-free correction (ude_fit.models.corrections.RestFreeCorrection): whatever its
network, it leaves the equilibrium at rest and its linearisation to the mechanistic model
and its explicit linear terms (affine in the airspeed)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ude_fit.analysis.continuation import hopf_point
from ude_fit.model_file import load_model, save_model
from ude_fit.models.flow import rk4_orbit
from ude_fit.models.corrections import MLPCorrection, RestFreeCorrection, Scaling
from ude_fit.models.mechanistic import Drive, FlutterQS
from ude_fit.models.ude import UDE
from ude_fit.training.options import FitOptions, TrainConfig

jax.config.update("jax_enable_x64", True)


def _network(key=0, size=50.0):
    # a network far from zero at rest, in force units of the aerofoil
    sc = Scaling(jnp.array([0.0, 0.0, 0.0, 0.0, 20.0]), jnp.array([0.03, 0.05, 0.5, 1.0, 3.0]),
                 jnp.array([size, 1.0]))
    return MLPCorrection(5, 2, sc, key=jax.random.PRNGKey(key), init_scale=30.0)


def test_value_and_slope_at_rest_are_the_linear_terms_alone():
    linear = jnp.array(np.random.default_rng(0).normal(size=(2, 2, 4)))
    c = RestFreeCorrection(_network(), 2, linear)
    s = c.scaling
    for V in (15.0, 22.0, 28.0):
        rest = jnp.array([0.0, 0.0, 0.0, 0.0, V])
        assert np.allclose(c(rest), 0.0, atol=1e-12)
        J = jax.jacfwd(lambda y: c(jnp.concatenate([y, jnp.array([V])])))(jnp.zeros(4))
        p = (V - s.z_mean[-1]) / s.z_scale[-1]
        # by hand: out_scale_i (L0 + p L1)_ij / y_scale_j, force per state unit
        want = np.array([[-s.out_scale[i] * (linear[0, i, j] + p * linear[1, i, j])
                          / s.z_scale[j] for j in range(4)] for i in range(2)])
        assert np.allclose(J, want, atol=1e-9)
        assert np.allclose(c.linear_matrix(V), want, atol=1e-12)
    # away from rest the network's nonlinear part is there
    y = jnp.array([0.02, 0.03, 0.3, 0.5, 22.0])
    assert np.abs(np.asarray(c(y) - c.linear_matrix(22.0) @ y[:4])).max() > 1e-3


def test_fixed_at_one_airspeed_it_is_the_same_correction():
    # an orbit's integration uses the correction with its rest terms computed once for the
    # orbit's airspeed (UDE.at_drive): values, the orbit, and the orbit's derivatives in the
    # airspeed (the continuation's shooting Jacobian) must be those of the full correction
    c = RestFreeCorrection(_network(), 2, jnp.array(np.random.default_rng(1).normal(
        size=(2, 2, 4))))
    fixed = c.at_parameter(22.0)
    for y in (jnp.zeros(4), jnp.array([0.02, 0.03, 0.3, 0.5]), jnp.array([-0.05, 0.1, 1.0, -2.0])):
        z = jnp.concatenate([y, jnp.array([22.0])])
        assert np.allclose(fixed(z), c(z), rtol=1e-12, atol=1e-12)
    model = UDE(FlutterQS.nominal(), c)
    y0 = jnp.array([0.01, 0.02, 0.0, 0.0])

    def end(V, frozen):
        # frozen: the integrator's path; else the full correction at every step
        m = model if frozen else UDE(model.mech, lambda z: c(z))
        return rk4_orbit(m, y0, 0.5, Drive.of(V), 64)[0]

    assert np.allclose(end(22.0, True), end(22.0, False), rtol=1e-12, atol=1e-14)
    dV = jax.jacfwd(lambda V: end(V, True))(22.0)
    assert np.allclose(dV, jax.jacfwd(lambda V: end(V, False))(22.0), rtol=1e-10, atol=1e-14)
    assert np.abs(np.asarray(dV)).max() > 1e-6


def test_the_hopf_point_is_the_mechanistic_models_whatever_the_network():
    mech = FlutterQS.nominal()
    ref = hopf_point(UDE(mech), (15.0, 30.0))
    free = hopf_point(UDE(mech, RestFreeCorrection(_network(), 2)), (15.0, 30.0))
    plain = hopf_point(UDE(mech, _network()), (15.0, 30.0))
    assert free["param"] == pytest.approx(ref["param"], abs=1e-6)
    # the same network added as it is moves the Hopf point (so the test can fail)
    assert plain is None or abs(plain["param"] - ref["param"]) > 0.05
    # added heave and pitch damping moves it up
    damped = RestFreeCorrection(_network(), 2, jnp.zeros((2, 2, 4)).at[0, 0, 2].set(0.02))
    moved = hopf_point(UDE(mech, damped), (15.0, 40.0))
    assert moved is not None and moved["param"] > ref["param"] + 0.05


def test_model_file_round_trip(tmp_path):
    model = UDE(FlutterQS.nominal(), RestFreeCorrection(_network(), 2, jnp.ones((2, 2, 4))))
    save_model(tmp_path / "m.eqx", model)
    back, _ = load_model(tmp_path / "m.eqx")
    y = jnp.array([0.02, 0.03, 0.3, 0.5, 22.0])
    d = Drive.of(22.0)
    assert np.allclose(back.vector_field(0.0, y[:4], d), model.vector_field(0.0, y[:4], d))


def test_rest_free_is_for_the_aerofoils_network():
    with pytest.raises(ValueError, match="--rest-free applies to --system flutter"):
        FitOptions(system="oscillator", train=TrainConfig(rest_free=True))
    with pytest.raises(ValueError, match="--rest-free"):
        FitOptions(system="flutter", approximator="gp", train=TrainConfig(rest_free=True))


def test_the_aerofoils_default_network_is_rest_free_with_constraint_rounds():
    used = lambda **kw: FitOptions(**kw).train.for_system(kw["system"])
    flutter = used(system="flutter")
    assert flutter.rest_free is True and flutter.constraint_rounds == 7
    # where the rounds cannot run, the default has none (an explicit request is refused)
    assert used(system="flutter", starts_together=True).constraint_rounds == 0
    assert used(system="flutter", training="trajectory").constraint_rounds == 0
    gp = used(system="flutter", approximator="gp")
    assert (gp.rest_free, gp.constraint_rounds) == (False, 0)
    amplitude = used(system="flutter", train=TrainConfig(form="amplitude"))
    assert (amplitude.rest_free, amplitude.constraint_rounds) == (False, 0)
    oscillator = used(system="oscillator")
    assert (oscillator.rest_free, oscillator.constraint_rounds) == (False, 0)
    # the user's choice stands
    plain = used(system="flutter", train=TrainConfig(rest_free=False, constraint_rounds=0))
    assert (plain.rest_free, plain.constraint_rounds) == (False, 0)
    # and what a fit records is what was used
    assert FitOptions("flutter").to_json()["train"]["rest_free"] is True
