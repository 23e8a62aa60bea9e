"""Errors in the measured bifurcation parameter (``--parameter-errors``, experimental).

A CBC point's airspeed is a measurement too: the tunnel drifts, the probe has its own error,
and the rig changes over a campaign. Points that scatter about smooth branches then ask a
model that must pass through each of them at its recorded airspeed to bend between them.
Here every orbit's parameter is an unknown of the periodic stage, ``P_i + sigma * u_i``,
with a Gaussian prior: the orbit's misfit gains ``cost_i * u_i**2``.

Both scales come from the data's own scatter about smooth branches, read both ways:

* ``sigma`` (:func:`~ude_fit.data.estimates.parameter_scatter`): the residual standard
  deviation of the parameter about a quadratic in the amplitude through each stability
  class (a branch's parameter is a single-valued function of its amplitude on either side
  of a fold or Hopf point), with its degrees of freedom;
* ``cost_i``: what missing orbit i's amplitude by the amplitude scatter
  (:func:`~ude_fit.data.estimates.data_scatter`) adds to its misfit, the whole orbit
  scaled.

So a one-sigma shift of the parameter costs what a one-sigma miss of the amplitude does, and
the fit splits a point's distance from the model's branch between the two as orthogonal
regression with both variances known would (Deming's). Where no class has the points to
estimate it, sigma is 0 and the parameters stay exact.
"""
from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from ..data.estimates import data_scatter, parameter_scatter
from ..data.orbit import OrbitDataset
from .identify import ParameterErrors, TrainingData


def parameter_errors(data: TrainingData, ds: OrbitDataset) -> ParameterErrors:
    """Every measured orbit's parameter scatter and the cost of a one-sigma offset, for
    ``data`` (the training arrays of ``ds``, hidden states included, no guide orbits)."""
    if not ds.kind.autonomous:
        raise ValueError("parameter errors apply to a self-excited system, whose parameter "
                         "enters only the vector field (a forced system's drive is measured "
                         "as a series)")
    if data.n_orbits != len(ds):
        raise ValueError("parameter_errors: the training data and the dataset differ")
    sigma = parameter_scatter(ds)
    amp = ds.amplitudes()
    rel = data_scatter(ds) * float(amp.max()) / amp        # the amplitude scatter, per orbit
    size = np.mean((np.asarray(data.ys) / np.asarray(data.y_scale)) ** 2, axis=(1, 2))
    return ParameterErrors(jnp.full(len(ds), sigma), jnp.asarray(rel ** 2 * size))
