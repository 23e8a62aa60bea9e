"""Fixed-step flows of a model over one period (the shooting map).

A fixed number of classical Runge-Kutta steps per period makes the discrete
flow map a smooth function of the initial state, the period and the parameter,
so Newton's method on it converges quadratically and ``jax.jacfwd`` gives the
exact Jacobian of what is solved (including the monodromy matrix).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import ClassVar

import diffrax
import jax
import jax.numpy as jnp
import numpy as np

from .mechanistic import Drive
from .ude import UDE


def _at_drive(model, drive: Drive):
    """``model`` with what it computes once per drive done before the loop
    (:meth:`UDE.at_drive`); any other object with a ``vector_field`` (a rig's truth, say)
    is integrated as it is."""
    at = getattr(model, "at_drive", None)
    return model if at is None else at(drive)


def rk4_orbit(model: UDE, y0, T, drive: Drive, n: int):
    """Integrate ``n`` RK4 steps over ``[0, T]``; returns (y(T), samples at t_j = j T / n)."""
    dt = T / n
    f = _at_drive(model, drive).vector_field

    def step(y, j):
        t = j * dt
        k1 = f(t, y, drive)
        k2 = f(t + 0.5 * dt, y + 0.5 * dt * k1, drive)
        k3 = f(t + 0.5 * dt, y + 0.5 * dt * k2, drive)
        k4 = f(t + dt, y + dt * k3, drive)
        return y + dt / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4), y

    yT, ys = jax.lax.scan(step, y0, jnp.arange(n))
    return yT, ys


def _rk4_stages(model: UDE, y0, T, drive: Drive, n: int):
    """:func:`rk4_orbit`'s steps, with every step's four stage states and their times:
    (y(T), samples (n, s), stage states (n, 4, s), stage times (n, 4))."""
    dt = T / n
    f = _at_drive(model, drive).vector_field

    def step(y, j):
        t = j * dt
        y1, k1 = y, f(t, y, drive)
        y2 = y + 0.5 * dt * k1
        k2 = f(t + 0.5 * dt, y2, drive)
        y3 = y + 0.5 * dt * k2
        k3 = f(t + 0.5 * dt, y3, drive)
        y4 = y + dt * k3
        k4 = f(t + dt, y4, drive)
        times = t + dt * jnp.array([0.0, 0.5, 0.5, 1.0])
        return (y + dt / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4),
                (y, jnp.stack([y1, y2, y3, y4]), times))

    yT, (ys, stages, times) = jax.lax.scan(step, y0, jnp.arange(n))
    return yT, ys, stages, times


def rk4_propagator(J, h):
    """The derivative of one classical Runge-Kutta step of size ``h`` in its start state,
    from the vector field's Jacobians ``J`` (4, s, s) at the step's four stages: the step
    of the variational equation that rides along with it."""
    eye = jnp.eye(J.shape[-1])
    K1 = J[0]
    K2 = J[1] @ (eye + 0.5 * h * K1)
    K3 = J[2] @ (eye + 0.5 * h * K2)
    K4 = J[3] @ (eye + h * K3)
    return eye + h / 6.0 * (K1 + 2.0 * K2 + 2.0 * K3 + K4)


def ordered_product(P):
    """P[m-1] ... P[1] P[0] of a stack of matrices, as a balanced tree of products."""
    while P.shape[0] > 1:
        odd = P.shape[0] % 2
        paired = P[1::2] @ P[0:P.shape[0] - odd:2]
        P = jnp.concatenate([paired, P[-1:]]) if odd else paired
    return P[0]


def rk4_orbit_monodromy(model: UDE, y0, T, drive: Drive, n: int):
    """:func:`rk4_orbit` with the monodromy matrix of its discrete flow, the derivative of
    y(T) in y0 (what ``jax.jacfwd`` of the flow gives, to rounding): (y(T), samples, M).

    The tangent integration is not carried through the steps: the steps' stage states are
    kept, the vector field's Jacobians at all of them are taken at once, and each step's
    derivative (:func:`rk4_propagator`) is multiplied out as a balanced tree. A step of the
    integration then carries one state instead of a state and s tangents, and on a CPU,
    where the step's chain of small operations is what the shooting loss costs, the loss's
    value and gradient take half the time."""
    yT, ys, stages, times = _rk4_stages(model, y0, T, drive, n)
    f = _at_drive(model, drive).vector_field
    jac = jax.vmap(jax.vmap(jax.jacfwd(lambda t, y: f(t, y, drive), argnums=1)))(times, stages)
    P = jax.vmap(rk4_propagator, (0, None))(jac, T / n)
    return yT, ys, ordered_product(P)


class ClassicalRK4(diffrax.AbstractERK):
    """The classical 4-stage Runge-Kutta method as a diffrax solver (fixed steps only: its
    error estimate is zero), so a trajectory integrated by diffrax takes exactly the steps of
    :func:`rk4_orbit`."""
    tableau: ClassVar[diffrax.ButcherTableau] = diffrax.ButcherTableau(
        a_lower=(np.array([0.5]), np.array([0.0, 0.5]), np.array([0.0, 0.0, 1.0])),
        b_sol=np.array([1 / 6, 1 / 3, 1 / 3, 1 / 6]),
        b_error=np.zeros(4),
        c=np.array([0.5, 0.5, 1.0]),
    )
    interpolation_cls: ClassVar[Callable] = (
        diffrax.ThirdOrderHermitePolynomialInterpolation.from_k)

    def order(self, terms):
        return 4


def diffrax_samples(model: UDE, y0, T, drive: Drive, n: int, sub: int):
    """States at t_j = j T / n, j = 0..n-1, integrated by diffrax with ``sub`` classical RK4
    steps between samples (reverse-mode differentiable, checkpointed)."""
    frozen = _at_drive(model, drive)
    term = diffrax.ODETerm(lambda t, y, args: frozen.vector_field(t, y, drive))
    ts = T * jnp.arange(n) / n
    sol = diffrax.diffeqsolve(term, ClassicalRK4(), t0=0.0, t1=ts[-1], dt0=T / (n * sub),
                              y0=y0, saveat=diffrax.SaveAt(ts=ts),
                              stepsize_controller=diffrax.ConstantStepSize(),
                              max_steps=n * sub)
    return sol.ys
