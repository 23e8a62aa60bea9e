"""Amplitude stages (``--amplitude-stages``, training.branch.amplitude_stages): the periodic
training first on the orbit nearest the Hopf point, then one more at a time in the order a
branch with one fold meets them (training.branch.branch_order). Checked against the measured
orbits' own amplitudes, against a scattered campaign's airspeeds and against the objective
on the subset alone."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tests.ude_fixtures import write_truth_campaign
from ude_fit import UDE, identify, load, training_data
from ude_fit._fourier import amplitude
from ude_fit.training.branch import BranchData, amplitude_stages, branch_order
from ude_fit.training.identify import TrainingData
from ude_fit.training.losses import periodic_objective
from ude_fit.training.options import FitOptions, TrainConfig
from ude_fit.training.train import train_ude

jax.config.update("jax_enable_x64", True)

pytestmark = pytest.mark.minutes(2)   # CI order: tests/conftest.py

CFG = TrainConfig().for_system("flutter")


@pytest.fixture(scope="module")
def problem(tmp_path_factory):
    path = tmp_path_factory.mktemp("stages") / "f.h5"
    write_truth_campaign(path, "flutter", airspeeds=(18.0, 21.0, 23.6))
    ds = load([path], "flutter")
    data = training_data(ds)
    mech, _ = identify(data, "flutter")
    # every orbit's first-harmonic heave amplitude, from the file's Fourier coefficients
    amps = amplitude(np.asarray([o.coeffs[0] for o in ds.orbits]))
    return data, mech, amps


def _params(data, key):
    k1, k2 = jax.random.split(key)
    return {"dy0": 1e-2 * jax.random.normal(k1, data.ys[:, 0, :].shape),
            "dT": 1e-3 * jax.random.normal(k2, data.period.shape)}


def test_the_stages_add_the_orbits_in_order_of_amplitude(problem):
    data, _, amps = problem
    masks = amplitude_stages(data)
    assert len(masks) == data.n_orbits - 1
    for k, m in enumerate(masks, start=1):
        assert m.sum() == k
        # the k smallest orbits, and every stage holds the one before it
        assert amps[m].max() < amps[~m].min()
        if k > 1:
            assert np.all(m[masks[k - 2]])


def test_scattered_orbits_are_met_in_order_of_airspeed_along_a_one_fold_branch():
    # a subcritical campaign: unstable orbits growing from the Hopf point (26 m/s) as the
    # airspeed falls, the one at 21.6 m/s smaller than its neighbours in airspeed (scatter);
    # stable orbits growing with the airspeed from the fold; one of unknown stability
    V = np.array([25.8, 24.1, 22.4, 21.6, 20.6, 20.7, 22.4, 23.2, 19.0])
    A = np.array([7.0, 18.0, 29.0, 25.0, 30.0, 51.0, 76.0, 86.0, 40.0]) * 1e-3
    label = np.array([-1, -1, -1, -1, -1, 1, 1, 1, 0.0])
    shuffle = np.random.default_rng(3).permutation(len(V))
    bd = BranchData(amps=A[shuffle], V=V[shuffle], label=label[shuffle], v_range=(10.0, 30.0),
                    v_span=20.0, scales=np.ones(4), grid=A)
    order = shuffle[branch_order(bd)]
    assert list(order) == list(range(len(V)))
    # by amplitude, the scattered orbit would come before two of its neighbours in airspeed
    assert list(np.argsort(A[:5])) != list(range(5))
    # a supercritical campaign (stable orbits only): by airspeed, as the amplitude grows
    V2, A2 = np.array([24.0, 25.0, 26.0]), np.array([0.02, 0.01, 0.03])
    bd2 = BranchData(amps=A2, V=V2, label=np.ones(3), v_range=(10.0, 30.0), v_span=20.0,
                     scales=np.ones(4), grid=A2)
    assert list(branch_order(bd2)) == [0, 1, 2]


def test_a_stage_is_the_objective_on_its_orbits_alone(problem):
    data, mech, amps = problem
    model = UDE(mech)
    params = _params(data, jax.random.PRNGKey(0))
    for m in amplitude_stages(data)[::2]:
        staged = float(periodic_objective(model, params, data.only(m), CFG))
        keep = np.flatnonzero(m)
        subset = TrainingData(data.ys[keep], data.qdd[keep], data.period[keep],
                              jax.tree_util.tree_map(lambda x: x[keep], data.drive),
                              data.label[keep], data.y_scale, data.amp_max)
        alone = float(periodic_objective(
            model, {k: v[keep] for k, v in params.items()}, subset, CFG))
        assert staged == pytest.approx(alone, rel=1e-12)


def test_an_orbit_not_yet_in_the_stages_cannot_make_the_gradient_non_finite(problem):
    data, mech, amps = problem
    big = int(np.argmax(amps))
    # the largest orbit's states so far out that the model's orbit from them overflows
    wild = eqx.tree_at(lambda d: d.ys, data, data.ys.at[big].multiply(1e80))
    params = _params(data, jax.random.PRNGKey(1))
    grad = lambda d: jax.grad(lambda p: periodic_objective(UDE(mech), p, d, CFG))(params)
    # a weight of 0 alone does not help (0 times a non-finite gradient) ...
    zero = eqx.tree_at(lambda d: d.weight, wild, jnp.asarray(~(np.arange(data.n_orbits) == big),
                                                              float),
                       is_leaf=lambda x: x is None)
    assert not all(bool(jnp.all(jnp.isfinite(g))) for g in jax.tree_util.tree_leaves(grad(zero)))
    # ... a stand-in in its place does
    stage = wild.only(np.arange(data.n_orbits) != big)
    assert all(bool(jnp.all(jnp.isfinite(g))) for g in jax.tree_util.tree_leaves(grad(stage)))


def test_the_stages_run_before_the_periodic_stage_on_every_orbit(problem):
    data, mech, amps = problem
    stages = []
    cfg = TrainConfig(amplitude_stages=True, adam_steps=2, lbfgs_steps=2, equation_steps=2,
                      equation_lbfgs_steps=0)
    model, info = train_ude(UDE(mech), data, key=jax.random.PRNGKey(0), cfg=cfg,
                            training="periodic",
                            progress=lambda **kw: stages.append(kw["stage"]))
    order = list(dict.fromkeys(stages))
    assert order == (["equation"]
                     + [f"periodic, {k} smallest orbits" for k in range(1, data.n_orbits)]
                     + ["periodic"])
    assert np.isfinite(info["final_loss"])


@pytest.mark.parametrize("fields, message", [
    (dict(system="oscillator"), "applies to --system flutter with --training periodic"),
    (dict(system="flutter", training="trajectory"),
     "applies to --system flutter with --training periodic"),
    (dict(system="flutter", approximator="gp"), "apply to --approximator nn only"),
])
def test_amplitude_stages_are_refused_where_they_do_not_apply(fields, message):
    with pytest.raises(ValueError, match=message):
        FitOptions(train=TrainConfig(amplitude_stages=True), **fields)
    with pytest.raises(ValueError, match="amplitude_stages must be True or False"):
        TrainConfig(amplitude_stages=1)
