"""Each orbit's parts of the periodic objective (ude_fit.training.losses.orbit_terms), against
the aerofoil model's own limit cycles traced by the continuation: an exact orbit fits and
closes, and its stability indicator has the sign of the traced stability."""
from __future__ import annotations

import dataclasses

import jax  # noqa: E402
import jax.numpy as jnp
import numpy as np
import pytest

from ude_fit import UDE, flutter_qs, trace_flutter
from ude_fit.models.flow import rk4_orbit
from ude_fit.models.mechanistic import Drive
from ude_fit.training.identify import TrainingData
from ude_fit.training.losses import orbit_terms, orbit_unknowns, periodic_objective
from ude_fit.training.options import TrainConfig

jax.config.update("jax_enable_x64", True)

SAMPLES, SUBSTEPS = 50, 4         # 200 RK4 steps a period: the continuation's own


@pytest.fixture(scope="module")
def traced():
    model = UDE(flutter_qs())
    branch = trace_flutter(model, v_range=(5.0, 40.0), amp_max=0.12,
                           scales=np.array([0.02, 0.1, 0.3, 1.5]), n=SAMPLES * SUBSTEPS)
    # one unstable orbit (between the Hopf point and the fold) and one stable one beyond it
    picks = [int(np.flatnonzero(~branch.stable)[len(np.flatnonzero(~branch.stable)) // 2]),
             int(np.flatnonzero(branch.stable)[len(np.flatnonzero(branch.stable)) // 2])]
    ys = []
    for k in picks:
        _, samples = rk4_orbit(model, jnp.asarray(branch.y0[k]), branch.period[k],
                               Drive.of(branch.param[k]), SAMPLES * SUBSTEPS)
        ys.append(np.asarray(samples)[::SUBSTEPS])
    ys = np.asarray(ys)
    drive = Drive(jnp.asarray(branch.param[picks]),
                  jnp.asarray(2 * np.pi / branch.period[picks]), jnp.zeros((2, 15)))
    label = np.where(branch.stable[picks], 1.0, -1.0)
    data = TrainingData(jnp.asarray(ys), jnp.zeros(ys.shape[:2] + (2,)),
                        jnp.asarray(branch.period[picks]), drive, jnp.asarray(label),
                        jnp.asarray(np.sqrt(np.mean(ys ** 2, axis=(0, 1)))),
                        float(branch.amplitude[picks].max()))
    return model, data, label


def test_an_exact_orbit_fits_and_closes_with_its_traced_stability(traced):
    model, data, label = traced
    cfg = TrainConfig(substeps=SUBSTEPS).for_system("flutter")
    t = orbit_terms(model, orbit_unknowns(data, True), data, cfg)
    assert np.all(np.asarray(t.fit) < 1e-20)
    assert np.all(np.asarray(t.closure) < 1e-12)     # the continuation's Newton tolerance
    assert np.all(np.sign(np.asarray(t.indicator)) == label)
    assert np.all(np.asarray(t.prior) == 0.0)


def test_the_objective_is_made_of_the_terms(traced):
    """The periodic objective is each orbit's misfit, closure and stability hinge, from the
    same terms; an orbit labelled against its stability pays the hinge."""
    model, data, label = traced
    cfg = TrainConfig(substeps=SUBSTEPS).for_system("flutter")
    params = orbit_unknowns(data, True)
    params["dy0"] = params["dy0"] + 1e-3            # off the orbits, so every term counts
    wrong = data.__class__(data.ys, data.qdd, data.period, data.drive, -data.label,
                           data.y_scale, data.amp_max)
    t = orbit_terms(model, params, wrong, cfg)
    hinge = np.maximum(cfg.stability_margin + label * np.asarray(t.indicator), 0.0) ** 2
    assert np.all(hinge > 0)
    expected = np.mean(np.asarray(t.fit) + cfg.closure_weight * np.asarray(t.closure)
                       + cfg.stability_weight * hinge)
    assert float(periodic_objective(model, params, wrong, cfg)) == pytest.approx(expected,
                                                                                rel=1e-12)


def test_each_orbit_is_held_at_its_own_margin(traced):
    """With per-orbit margins (analysis.margins) the hinge of an orbit is measured from its
    own margin; nan stands for the configured one."""
    model, data, label = traced
    cfg = TrainConfig(substeps=SUBSTEPS).for_system("flutter")
    params = orbit_unknowns(data, True)
    t = orbit_terms(model, params, data, cfg)
    held = label * np.asarray(t.indicator)            # > 0: both on their labelled side
    assert np.all(held > cfg.stability_margin)       # the constant margin costs nothing
    own = dataclasses.replace(data, margin=jnp.asarray([2 * held[0], np.nan]))
    plain = float(periodic_objective(model, params, data, cfg))
    expected = plain + cfg.stability_weight * held[0] ** 2 / 2      # mean over 2 orbits
    assert float(periodic_objective(model, params, own, cfg)) == pytest.approx(expected,
                                                                              rel=1e-9)
