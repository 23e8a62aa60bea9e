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
