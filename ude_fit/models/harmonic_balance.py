"""A model's periodic orbits by one-harmonic balance, parametrised by the first coordinate's
(heave's) first-harmonic amplitude: at each amplitude a, the airspeed V(a), the frequency and
the other states' first harmonics and means at which the model's vector field balances the
ansatz y(t) = c + C cos(omega t) + S sin(omega t) in its mean and first harmonic.

The branch is followed in amplitude from the model's Hopf point (each Newton solve starts
from the last solution moved along the branch's tangent), so it is the model's own branch,
whatever the mechanism of its nonlinearity: a conservative stiffness bends it through the
frequency and the states' phases, which a work balance along a fixed shape cannot see. The
slope dV/da comes from the implicit function theorem. An autonomous model only (the
aerofoil): the airspeed is ``Drive.param``.

Unknowns z = (c (n), C[1:] (n-1), S[1:] (n-1), omega, V): the heave's cosine coefficient is
the amplitude a and its sine coefficient 0 (the phase), so there are 3n unknowns for the 3n
balances of the n states' means, cosines and sines.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from .mechanistic import Drive

SAMPLES = 16          # phases per period: harmonics up to the 14th do not alias onto the first


def unpack(z, a, n: int):
    """(c, C, S, omega, V) of the unknowns ``z`` at heave amplitude ``a``."""
    c = z[:n]
    C = jnp.concatenate([jnp.reshape(a, (1,)), z[n:2 * n - 1]])
    S = jnp.concatenate([jnp.zeros(1), z[2 * n - 1:3 * n - 2]])
    return c, C, S, z[3 * n - 2], z[3 * n - 1]


def residual(model, z, a, scale):
    """The mean, cosine and sine balances of every state (3n), each over omega * scale."""
    n = model.n_state
    c, C, S, omega, V = unpack(z, a, n)
    th = 2.0 * jnp.pi * jnp.arange(SAMPLES) / SAMPLES
    cos, sin = jnp.cos(th), jnp.sin(th)
    y = c[None] + cos[:, None] * C[None] + sin[:, None] * S[None]
    dy = omega * (-sin[:, None] * C[None] + cos[:, None] * S[None])
    d = Drive.of(V)
    r = dy - jax.vmap(lambda yy: model.vector_field(0.0, yy, d))(y)
    out = jnp.concatenate([jnp.mean(r, 0), 2.0 * jnp.mean(r * cos[:, None], 0),
                           2.0 * jnp.mean(r * sin[:, None], 0)])
    return out / (jnp.abs(omega) * jnp.tile(scale, 3))


def rest(model, V):
    """The equilibrium near rest at airspeed V and the Jacobian there (Newton from 0)."""
    d = Drive.of(V)
    f = lambda y: model.vector_field(0.0, y, d)
    y = jnp.zeros(model.n_state)
    for _ in range(3):
        y = y - jnp.linalg.solve(jax.jacfwd(f)(y), f(y))
    return y, jax.jacfwd(f)(y)


def hopf_start(model, V_grid, a):
    """Unknowns at heave amplitude ``a`` (small) on the branch from the model's first Hopf
    point over the increasing ``V_grid``: the equilibrium, the critical eigenvector scaled
    to heave amplitude a, its frequency and the Hopf airspeed (where the largest growth
    rate, linear between grid points, crosses zero). Where none crosses the guess is at
    the grid's first airspeed and the solves from it are not expected to converge."""
    growth = jax.vmap(lambda V: jnp.max(jnp.real(jnp.linalg.eigvals(rest(model, V)[1]))))(
        V_grid)
    cross = (growth[:-1] < 0) & (growth[1:] >= 0)
    i = jnp.argmax(cross)
    g0, g1 = growth[i], growth[i + 1]
    V_H = V_grid[i] + (V_grid[i + 1] - V_grid[i]) * (-g0) / jnp.where(g1 > g0, g1 - g0, 1.0)
    y_eq, J = rest(model, V_H)
    lam, vecs = jnp.linalg.eig(J)
    k = jnp.argmax(jnp.where(jnp.imag(lam) > 0, jnp.real(lam), -jnp.inf))
    h = vecs[:, k]
    h = h * jnp.exp(-1j * jnp.angle(h[0])) * (a / jnp.abs(h[0]))       # y = Re(h e^{iwt})
    return jnp.concatenate([y_eq, h.real[1:], -h.imag[1:],
                            jnp.stack([jnp.imag(lam[k]), V_H])])


def _newton(model, z, a, scale, steps: int):
    F = lambda zz: residual(model, zz, a, scale)
    # a loop, not unrolled: one compiled step whatever the count
    return jax.lax.fori_loop(0, steps, lambda _, zz: zz - jnp.linalg.solve(jax.jacfwd(F)(zz),
                                                                          F(zz)), z)


def _tangent(model, z, a, scale):
    """dz/da along the branch at the solution ``z`` (implicit function theorem)."""
    F = lambda zz, aa: residual(model, zz, aa, scale)
    return -jnp.linalg.solve(jax.jacfwd(F)(z, a), jax.jacfwd(F, argnums=1)(z, a))


def follow(model, amps, z0, scale, first_steps: int = 20, steps: int = 4,
           tol: float = 1e-8):
    """The branch at each amplitude of ``amps`` in turn (a monotone sequence), from the
    guess ``z0`` at the first: (z (k, 3n), converged (k,)). Each solve starts from the last
    converged solution moved along the branch's tangent (so that a steep stretch is not
    jumped over to another branch). A point counts as converged where every balance is
    within ``tol`` of the amplitude's own scale (heave's ``scale``); the last converged
    solution stands in for one that did not (so that everything returned is finite)."""
    def ok(z, a):
        r = residual(model, z, a, scale)
        return jnp.all(jnp.isfinite(z)) & (jnp.max(jnp.abs(r)) <= tol * a / scale[0])

    z_first = _newton(model, z0, amps[0], scale, first_steps)
    first_ok = ok(z_first, amps[0])
    z_first = jnp.where(first_ok, z_first, z0)

    def step(carry, a):
        z_last, a_last, dz = carry
        z = _newton(model, z_last + dz * (a - a_last), a, scale, steps)
        good = ok(z, a)
        z = jnp.where(good, z, z_last)
        dz_new = _tangent(model, z, a, scale)
        dz = jnp.where(good & jnp.all(jnp.isfinite(dz_new)), dz_new, dz)
        a = jnp.where(good, a, a_last)
        return (z, a, dz), (z, good)

    dz0 = _tangent(model, z_first, amps[0], scale)
    dz0 = jnp.where(first_ok & jnp.all(jnp.isfinite(dz0)), dz0, jnp.zeros_like(dz0))
    _, (zs, good) = jax.lax.scan(step, (z_first, amps[0], dz0), amps[1:])
    return (jnp.concatenate([z_first[None], zs]),
            jnp.concatenate([first_ok[None], good]))


def airspeed_slopes(model, zs, amps, scale):
    """dV/da at each solved point (implicit function theorem), after one Newton step taken
    with ``model`` itself: where ``zs`` were solved with the model's weights held fixed
    (``jax.lax.stop_gradient``), the slopes' derivatives in the weights are then exact at
    convergence."""
    def one(z, a):
        F = lambda zz: residual(model, zz, a, scale)
        z = z - jnp.linalg.solve(jax.jacfwd(F)(z), F(z))
        return _tangent(model, z, a, scale)[-1]
    return jax.vmap(one)(zs, amps)


def held(model):
    """``model`` with its weights out of differentiation (for :func:`follow`)."""
    dyn, static = eqx.partition(model, eqx.is_inexact_array)
    return eqx.combine(jax.lax.stop_gradient(dyn), static)
