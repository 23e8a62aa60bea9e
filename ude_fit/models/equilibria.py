"""The equilibrium branch of an aerofoil model and its Hopf point (eigenvalues of the
Jacobian over a grid of airspeeds; the first crossing refined by a root search). Here, below
the analysis layer, so that training can start a branch at the Hopf point too."""
from __future__ import annotations

import functools
from dataclasses import dataclass

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from scipy.optimize import brentq

from .mechanistic import Drive
from .ude import UDE


@eqx.filter_jit
def _equilibrium_scan(model, Vs, y_guess):
    """Equilibria and Jacobian eigenvalues over a grid of airspeeds (Newton, 30 steps)."""
    def one(V):
        d = Drive.of(V)
        f = lambda y: model.vector_field(0.0, y, d)

        def body(_, y):
            return y - jnp.linalg.solve(jax.jacfwd(f)(y), f(y))
        y = jax.lax.fori_loop(0, 30, body, y_guess)
        lam = jnp.linalg.eigvals(jax.jacfwd(f)(y))
        return y, lam, jnp.max(jnp.abs(f(y)))
    return jax.vmap(one)(Vs)


@dataclass
class Equilibria:
    param: np.ndarray
    max_real: np.ndarray        # largest real part of the Jacobian's eigenvalues (1/s)
    stable: np.ndarray
    residual: np.ndarray


# ---------------------------------------------------------------------------------------
# equilibrium branch and Hopf point (aerofoil)
# ---------------------------------------------------------------------------------------

def equilibrium_branch(model: UDE, v_range, n: int = 121) -> Equilibria:
    Vs = np.linspace(*v_range, n)
    y, lam, res = _equilibrium_scan(model, jnp.asarray(Vs), jnp.zeros(model.n_state))
    mr = np.asarray(jnp.max(jnp.real(lam), axis=1))
    return Equilibria(Vs, mr, mr < 0, np.asarray(res))


def hopf_point(model: UDE, v_range, n: int = 121) -> dict | None:
    """First loss of stability of the equilibrium in ``v_range``: {"param", "frequency", "y", "eigvec"}."""
    eq = equilibrium_branch(model, v_range, n)
    idx = np.nonzero((eq.max_real[:-1] < 0) & (eq.max_real[1:] >= 0))[0]
    if len(idx) == 0:
        return None
    k = int(idx[0])

    @functools.lru_cache(maxsize=None)      # brentq asks again for the two ends
    def g(V):
        _, lam, _ = _equilibrium_scan(model, jnp.asarray([V]), jnp.zeros(model.n_state))
        return float(jnp.max(jnp.real(lam)))

    a, b = eq.param[k], eq.param[k + 1]
    ga, gb = g(a), g(b)
    if ga < 0 <= gb:
        VH = brentq(g, a, b, xtol=1e-12, rtol=1e-13)
    else:
        # one airspeed alone does not give the scan's sign at an end (a growth rate within
        # rounding of zero there): the scan's own crossing, interpolated
        m0, m1 = eq.max_real[k], eq.max_real[k + 1]
        VH = float(a + (b - a) * (-m0) / (m1 - m0)) if m1 != m0 else float(b)
    y, lam, _ = _equilibrium_scan(model, jnp.asarray([VH]), jnp.zeros(model.n_state))
    d = Drive.of(VH)
    Jm = np.asarray(jax.jacfwd(lambda yy: model.vector_field(0.0, yy, d))(y[0]))
    w, v = np.linalg.eig(Jm)
    j = int(np.argmax(np.real(w) + 1e-9 * np.sign(np.imag(w))))
    if np.imag(w[j]) < 0:
        j = int(np.argmin(np.abs(w - np.conj(w[j]))))
    return {"param": float(VH), "frequency": float(abs(np.imag(w[j])) / (2 * np.pi)),
            "y": np.asarray(y[0]), "eigvec": v[:, j], "omega": float(abs(np.imag(w[j])))}


