"""Guide orbits: the one-fold curve's orbits, where the measurements are silent.

The periodic loss asks for a model orbit through every measured one and says nothing
between them, above the largest or near the Hopf point, and there a trained correction
bends the branch into folds the data does not show. A guide orbit stands at an amplitude
of the one-fold curve fitted to the points (:mod:`ude_fit.data.one_fold`), at the
curve's airspeed, with the stability of its side of the curve's fold (none within half a
step of it). Its shape is the nearest measured orbit of that stability scaled to the
amplitude, and only its heave and heave rate are asked of the model: the pitch and its
phase, which scaling cannot carry from one orbit to another, stay free. Each guide weighs
``weight`` against a measured orbit's 1, so the data wins where the two disagree.

Guides enter the periodic training and the constraint rounds; the equation stage, the
feature scaling and the regularity conditions see the measurements alone
(:meth:`~.identify.TrainingData.measurements`), and so do the metrics.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from ..data.one_fold import OneFoldCurve
from ..data.orbit import OrbitDataset
from .identify import ParameterErrors, TrainingData, augment, training_data

# the largest guide's amplitude over the largest measured one: a little above the data,
# where the curve is extrapolated; the smallest guide is the smallest measured orbit's (below
# it the curve's way to the Hopf point is an extrapolation the points do not pin)
GUIDE_TOP = 1.15


def guide_orbits(ds: OrbitDataset, curve: OneFoldCurve, n: int,
                 top: float = GUIDE_TOP) -> OrbitDataset:
    """``n`` orbits of ``curve``, evenly spaced in amplitude from the smallest labelled
    orbit's to ``top`` times the largest."""
    labelled = [o for o in ds if o.stable is not None]
    lo, hi = min(o.amplitude for o in labelled) / curve.amp_scale, top
    grid = np.linspace(lo, hi, n)
    step = (hi - lo) / max(n - 1, 1)
    out = []
    for s in grid:
        unstable = bool(curve.unstable(s))
        same = [o for o in labelled if (o.stable is False) == unstable] or labelled
        near = min(same, key=lambda o: abs(o.amplitude / curve.amp_scale - s))
        stable = None if abs(s - curve.fold_s) < 0.5 * step else not unstable
        out.append(dataclasses.replace(
            near, parameter=float(curve.airspeed(s)),
            coeffs=near.coeffs * (s * curve.amp_scale / near.amplitude),
            stable=stable, source=f"guide at {s * curve.amp_scale * 1e3:.1f} mm",
            stability_from="one-fold curve" if stable is not None else "",
            holding=None, control=None, noise=np.full(near.coeffs.shape[0], np.nan)))
    return OrbitDataset(ds.system, tuple(out), tuple(o.source for o in out))


def with_guides(data: TrainingData, guides: OrbitDataset, mech, weight: float) -> TrainingData:
    """``data`` (the measurements, hidden states included) followed by ``guides``, each at
    ``weight``, with only the heave and its rate in their misfit."""
    if not weight > 0:
        raise ValueError(f"the guide orbits' weight must be positive, not {weight!r}")
    g = augment(training_data(guides, data.ys.shape[1]), mech)
    if data.drive.fc.shape[1:] != g.drive.fc.shape[1:]:
        raise ValueError("with_guides: the measurements and guides have different drives")
    n_dof = mech.n_dof
    sw = np.zeros((g.n_orbits, g.ys.shape[2]))
    sw[:, 0] = sw[:, n_dof] = 1.0                 # heave and heave rate
    n = data.n_orbits
    cat = lambda a, b: jnp.concatenate([a, b])
    return TrainingData(
        cat(data.ys, g.ys), cat(data.qdd, g.qdd), cat(data.period, g.period),
        jax.tree_util.tree_map(cat, data.drive, g.drive), cat(data.label, g.label),
        data.y_scale, data.amp_max,
        cat(jnp.ones(n) if data.weight is None else data.weight,
            jnp.full(g.n_orbits, float(weight))),
        cat(jnp.ones(data.ys.shape[::2]), jnp.asarray(sw)), n,
        # a guide sits where the one-fold curve puts it: its airspeed is exact
        None if data.param_errors is None else ParameterErrors(
            cat(data.param_errors.sigma, jnp.zeros(g.n_orbits)),
            cat(data.param_errors.cost, jnp.zeros(g.n_orbits))),
        None if data.margin is None else cat(data.margin, jnp.full(g.n_orbits, jnp.nan)))
