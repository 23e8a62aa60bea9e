"""The quasi-steady aerofoil's own limit cycles as training data, for the tests of the
periodic objective's terms (shooting and collocation): the branch traced by the
continuation, chosen orbits integrated at a fine step and sampled as the fits sample the
data, each with its traced stability as its label."""
from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from ude_fit import UDE, flutter_qs, trace_flutter
from ude_fit.models.flow import rk4_orbit
from ude_fit.models.mechanistic import Drive
from ude_fit.training.identify import TrainingData


def traced_orbits(samples: int, substeps: int, choose):
    """(model, data, label): ``choose(branch)`` gives the indices of the branch points to
    take; each is integrated over its period in ``samples * substeps`` RK4 steps and kept at
    every ``substeps``-th."""
    model = UDE(flutter_qs())
    branch = trace_flutter(model, v_range=(5.0, 40.0), amp_max=0.12,
                           scales=np.array([0.02, 0.1, 0.3, 1.5]), n=samples * substeps)
    picks = [int(k) for k in choose(branch)]
    ys = []
    for k in picks:
        _, orbit = rk4_orbit(model, jnp.asarray(branch.y0[k]), branch.period[k],
                             Drive.of(branch.param[k]), samples * substeps)
        ys.append(np.asarray(orbit)[::substeps])
    ys = np.asarray(ys)
    drive = Drive(jnp.asarray(branch.param[picks]),
                  jnp.asarray(2 * np.pi / branch.period[picks]), jnp.zeros((len(picks), 15)))
    label = np.where(branch.stable[picks], 1.0, -1.0)
    data = TrainingData(jnp.asarray(ys), jnp.zeros(ys.shape[:2] + (2,)),
                        jnp.asarray(branch.period[picks]), drive, jnp.asarray(label),
                        jnp.asarray(np.sqrt(np.mean(ys ** 2, axis=(0, 1)))),
                        float(branch.amplitude[picks].max()))
    return model, data, label
