"""Where an amplitude-form correction (:mod:`ude_fit.models.amplitude`) starts: its linear
terms from the Hopf point the unstable orbits extrapolate to, and its damping coefficient
from the energy balance of every measured orbit. No weight is tuned: both are what the data
measures.

Energy balance: a closed orbit of ``M q'' = F + U`` (M constant along it) has
``oint q'.(M q'') dt = 0``, so the correction's work per cycle along a measured orbit must
equal the residual force's, ``W_k[U] = W_k[R]`` with ``R = M q'' - F``. For the amplitude
form ``W_k[U] = W_k[L y] - sum_j phi(e_kj) q'_kj.C q'_kj dt``: linear in phi's slopes, one
equation per orbit. Solved by non-negative least squares (the ramps' slopes are >= 0, which
keeps phi convex), each orbit's row over its own dissipation scale so that small and large
orbits count alike.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from scipy.optimize import nnls

from ..models.amplitude import AmplitudeCorrection, pin_hopf
from ..models.ude import UDE
from .identify import TrainingData, residual_forces
from .penalties import hopf_from_unstable


def start_amplitude(model: UDE, data: TrainingData) -> UDE:
    """The amplitude form's starting point on ``model`` (a UDE holding a fresh amplitude
    correction): the Hopf point pinned where the unstable orbits put it (where they say),
    then the damping coefficient from every orbit's energy balance."""
    v_hopf = hopf_from_unstable(data)
    if np.isfinite(v_hopf):
        model = pin_hopf(model, v_hopf)
    return balance_work(model, data)


def balance_work(model: UDE, data: TrainingData) -> UDE:
    """``model`` with its amplitude correction's damping coefficient (phi's linear slope and
    ramp slopes) set so that every measured orbit balances its energy; C and the linear
    terms as they are."""
    c: AmplitudeCorrection = model.correction
    n = c.n_dof
    Z, R = residual_forces(UDE(model.mech), data)
    k, m = data.ys.shape[:2]
    Z = np.asarray(Z).reshape(k, m, -1)
    R = np.asarray(R).reshape(k, m, n)
    dt = np.asarray(data.period, float)[:, None] / m
    qd = Z[:, :, n:2 * n]
    zs = jnp.asarray(Z.reshape(k * m, -1))
    lin = (Z[:, :, :2 * n] @ np.asarray(c.linear_matrix()).T)          # L y
    cq = np.asarray(jax.vmap(c.damping_direction)(zs)).reshape(k, m, n)
    e = np.asarray(jax.vmap(c.size_of)(zs))
    power = np.sum(cq * qd, axis=2) * dt                      # q'.C q' dt, (k, m), >= 0
    ramps = np.asarray(jax.vmap(c.basis.ramps)(jnp.asarray(e))).reshape(k, m, -1)
    basis = np.concatenate([e.reshape(k, m, 1), -e.reshape(k, m, 1), ramps], axis=2)
    A = -np.einsum("kmb,km->kb", basis, power)               # W_k of -phi C q', per slope
    b = np.sum((R - lin) * qd, axis=2).sum(axis=1) * dt[:, 0]  # W_k[R] - W_k[L y]
    scale = np.sum(power, axis=1) * np.maximum(e.reshape(k, m).mean(axis=1), 1e-12)
    scale = np.where(scale > 0, scale, 1.0)
    theta, _ = nnls(A / scale[:, None], b / scale)
    slopes = np.maximum(theta[2:], 1e-12)
    fitted = eqx.tree_at(lambda u: (u.phi_lin, u.phi_raw), c,
                         (jnp.asarray(theta[0] - theta[1]),
                          jnp.asarray(np.log(np.expm1(slopes)))))
    return model.with_correction(fitted)
