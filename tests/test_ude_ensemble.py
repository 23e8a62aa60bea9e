"""Many random starts trained as one vectorised ensemble (ude_fit.training.optimise.descend,
ude_fit.training.train.train_ensemble): each start is what training it alone gives, a start
whose loss goes non-finite is dropped without touching the others."""

from __future__ import annotations

import equinox as eqx
import numpy as np
import pytest

from tests.ude_fixtures import write_truth_campaign
from ude_fit import UDE, Diverged, TrainConfig, identify, load, training_data
from ude_fit.training.optimise import descend, minimize
from ude_fit.training.train import train_ensemble, train_ude

import jax  # noqa: E402  (after the imports above, before any array)
import jax.numpy as jnp  # noqa: E402

jax.config.update("jax_enable_x64", True)       # ude_fit computes in float64 (see ude_fit docs)

pytestmark = pytest.mark.minutes(2)   # CI order: tests/conftest.py


def _weights(model: UDE) -> list[np.ndarray]:
    return [np.asarray(x) for x in jax.tree_util.tree_leaves(
        eqx.filter(model.correction, eqx.is_inexact_array))]


@pytest.mark.parametrize("stages", [False, True])
def test_ensemble_start_k_is_the_single_start_with_key_k(tmp_path, stages):
    # the default (periodic) training: both stages, L-BFGS line searches, per-orbit unknowns;
    # and with --amplitude-stages (the orbits added one at a time, shared by every start)
    training = "periodic"
    write_truth_campaign(tmp_path / "f.h5", "flutter", airspeeds=(18.0, 21.0, 23.6))
    data = training_data(load([tmp_path / "f.h5"], "flutter"), n=16)
    mech, _ = identify(data, "flutter")
    # the aerofoil's default network (rest-free); constraint rounds, which differ from start
    # to start, are not run for starts trained together
    cfg = TrainConfig(width=4, equation_steps=50, equation_lbfgs_steps=5, adam_steps=25,
                      lbfgs_steps=5, amplitude_stages=stages, constraint_rounds=0)
    keys = jax.random.split(jax.random.PRNGKey(3), 3)
    together = train_ensemble(UDE(mech), data, keys=keys, cfg=cfg, training=training)
    assert len(together) == 3
    finals = []
    for k in range(3):
        alone, info = train_ude(UDE(mech), data, key=keys[k], cfg=cfg, training=training)
        model, info_k = together[k]
        # to rounding: the rest-free network's Jacobian at rest, batched over the starts,
        # sums in another order than alone, and 90 training steps carry that to a few 1e-9
        for a, b in zip(_weights(alone), _weights(model), strict=True):
            np.testing.assert_allclose(b, a, rtol=1e-7, atol=1e-12)
        assert info_k["final_loss"] == pytest.approx(info["final_loss"], rel=1e-7)
        assert info_k["equation_loss"] == pytest.approx(info["equation_loss"], rel=1e-7)
        finals.append(info["final_loss"])
    assert len(set(finals)) == 3                 # the keys really gave different starts


def _bowl(p, centre):
    """A quadratic bowl about ``centre`` that is NaN wherever p["x"][0] > 5."""
    x = p["x"]
    return jnp.sum((x - centre) ** 2) + jnp.where(x[0] > 5.0, jnp.nan, 0.0)


def test_a_start_whose_loss_goes_non_finite_is_dropped_and_the_others_go_on():
    centre = jnp.array([1.0, -2.0])
    starts = jnp.array([[9.0, 0.0], [0.0, 0.0], [3.0, 3.0]])     # the first is NaN at once
    params, losses, failed = descend(_bowl, {"x": starts}, (centre,), lanes=3, adam_steps=50,
                                     lbfgs_steps=20, lr=0.1, stage="bowl")
    assert failed == {0: "bowl: loss is not finite at Adam step 25"}
    assert np.isnan(losses[0])
    for k in (1, 2):
        alone, loss = minimize(_bowl, {"x": starts[k]}, (centre,), adam_steps=50,
                               lbfgs_steps=20, lr=0.1, stage="bowl")
        np.testing.assert_allclose(np.asarray(params["x"][k]), np.asarray(alone["x"]),
                                   rtol=1e-12, atol=1e-12)
        assert losses[k] == pytest.approx(loss, rel=1e-12, abs=1e-14)
        np.testing.assert_allclose(np.asarray(alone["x"]), np.asarray(centre), atol=1e-6)
    with pytest.raises(Diverged, match="bowl: loss is not finite at Adam step 25"):
        minimize(_bowl, {"x": starts[0]}, (centre,), adam_steps=50, lbfgs_steps=20, lr=0.1,
                 stage="bowl")


def test_lbfgs_lanes_stop_at_their_best_or_fail_each_on_its_own():
    """L-BFGS runs lane by lane: lanes whose loss is not finite beyond a wall stay on its
    finite side, one that starts non-finite fails without touching them; each lane equals
    its single run."""
    centre = jnp.array([8.0, 0.0])              # beyond the NaN wall at x[0] = 5
    starts = jnp.array([[0.0, 0.0], [6.0, 0.0], [1.0, 1.0]])
    params, losses, failed = descend(_bowl, {"x": starts}, (centre,), lanes=3,
                                     adam_steps=0, lbfgs_steps=20, lr=0.1, stage="wall")
    assert failed == {1: "wall: loss is not finite at L-BFGS step 1"}
    assert np.isnan(losses[1])
    for k in (0, 2):
        assert np.isfinite(losses[k]) and float(params["x"][k][0]) <= 5.0
        assert losses[k] < float(_bowl({"x": starts[k]}, centre))
        alone, loss = minimize(_bowl, {"x": starts[k]}, (centre,), adam_steps=0,
                               lbfgs_steps=20, lr=0.1, stage="wall")
        np.testing.assert_allclose(np.asarray(params["x"][k]), np.asarray(alone["x"]),
                                   rtol=1e-12, atol=1e-12)
        assert losses[k] == pytest.approx(loss, rel=1e-12)
