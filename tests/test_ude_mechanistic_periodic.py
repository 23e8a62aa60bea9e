"""`--mechanistic periodic`: the output-error refinement keeps the physical signs that the
equation-error identification bounds (damping and stiffness positive), on the wind-tunnel
data whose heave damping the unconstrained refinement drives below zero."""
import glob

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ude_fit import FitOptions, load
from ude_fit.fitting import prepare
from ude_fit.mechanistic_stage import mechanistic_stage
from ude_fit.models.mechanistic import flutter_qs
from ude_fit.models.ude import UDE
from ude_fit.training.options import TrainConfig
from ude_fit.training.train import (_POSITIVE_FLOOR, _mech_leaves, _mech_with,
                                    _positive_mask, refine_mechanistic)

jax.config.update("jax_enable_x64", True)
pytestmark = pytest.mark.minutes(1)


def _flat(mech):
    leaves = _mech_leaves(mech)
    sizes = tuple(tuple(jnp.shape(x)) for x in leaves)
    base = jnp.concatenate([jnp.ravel(jnp.asarray(x, float)) for x in leaves])
    return sizes, base, jnp.where(jnp.abs(base) > 0, jnp.abs(base), 1.0)


def test_the_parameterisation_starts_at_the_estimate_and_never_crosses_zero():
    mech = flutter_qs()
    sizes, base, scale = _flat(mech)
    positive = jnp.asarray(_positive_mask(mech, sizes))
    names = list(mech.fitted)
    assert [n for n, p in zip(names, np.asarray(positive)) if p] == list(mech.must_be_positive)
    at_start = _mech_with(mech, sizes, base, scale, jnp.zeros(base.size), positive)
    for n in names:          # the start is the estimate (to the floor's second order)
        assert float(getattr(at_start, n)) == pytest.approx(float(getattr(mech, n)), rel=1e-6)
    far = _mech_with(mech, sizes, base, scale, -50.0 * jnp.ones(base.size), positive)
    for n in names:
        v = float(getattr(far, n))
        if n in mech.must_be_positive:
            assert 0.0 < v < 1e-4 * float(getattr(mech, n))
        else:                 # the free ones move linearly, either way
            assert v == pytest.approx(float(getattr(mech, n)) * -49.0, rel=1e-9)


def test_the_refinement_keeps_the_heave_damping_positive_on_lee2020(lee2020_dir):
    ds = load(sorted(glob.glob(str(lee2020_dir / "model2" / "*.mat"))), "flutter")
    opts = FitOptions(system="flutter", starts=1)
    _, data, *_ = prepare(ds, "flutter", None, opts.samples)
    data, mech, ident = mechanistic_stage(ds, data, opts)
    assert "c_h" in ident["at_bound"]           # the equation error wants it below zero
    cfg = TrainConfig(adam_steps=150, lbfgs_steps=60)
    model, info = refine_mechanistic(UDE(mech), data, cfg=cfg)
    refined = model.mech.parameters()
    for n in mech.must_be_positive:
        assert refined[n] > 0.0, (n, refined[n])
    assert refined["c_h"] >= _POSITIVE_FLOOR ** 2 / 4       # the map's floor, in N s/m
    assert np.isfinite(info["loss"])
