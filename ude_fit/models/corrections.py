"""Corrections U(z): the neural networks a UDE adds to its mechanistic model, and the
affine scaling that keeps their inputs and outputs of order one."""

from __future__ import annotations


import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np


class Scaling(eqx.Module):
    """Affine maps that keep the approximator's inputs and outputs of order one."""
    z_mean: jax.Array
    z_scale: jax.Array
    out_scale: jax.Array


def _small_last_layer(mlp: eqx.nn.MLP, init_scale: float) -> eqx.nn.MLP:
    """``mlp`` with its last layer scaled by ``init_scale``: a fresh UDE is then the
    mechanistic model plus a near-zero correction."""
    last = mlp.layers[-1]
    return eqx.tree_at(lambda m: (m.layers[-1].weight, m.layers[-1].bias), mlp,
                       (last.weight * init_scale, last.bias * init_scale))


class MLPCorrection(eqx.Module):
    """U(z) = out_scale * MLP((z - z_mean) / z_scale), sigmoid hidden units.

    The last layer starts at ``init_scale`` times its default size, so a fresh
    UDE is the mechanistic model plus a near-zero correction.
    """
    mlp: eqx.nn.MLP
    scaling: Scaling

    def __init__(self, n_in: int, n_out: int, scaling: Scaling, *, width: int = 12,
                 depth: int = 2, key, init_scale: float = 1e-2):
        mlp = eqx.nn.MLP(n_in, n_out, width, depth, activation=jax.nn.sigmoid, key=key)
        self.mlp = _small_last_layer(mlp, init_scale)
        self.scaling = scaling

    def __call__(self, z):
        s = self.scaling
        return s.out_scale * self.mlp((z - s.z_mean) / s.z_scale)


class PolynomialParamCorrection(eqx.Module):
    """A correction that is a polynomial of degree ``degree`` in the parameter (the last
    feature) with state-dependent coefficients:

        U(y; p) = out_scale * sum_k s^k N_k((y - y_mean) / y_scale),  s = (p - p_mean) / p_scale,

    the ``degree + 1`` coefficient functions being the output heads of one MLP of the
    state alone. Quasi-steady aerodynamic forces depend on the airspeed through V (on the
    velocities) and V^2 (on the displacements), so degree 2 spans them; unlike a network
    that takes the airspeed as an input, this one cannot bend back and forth in it, which
    is what makes a fitted branch snake through scattered measurements.
    """
    mlp: eqx.nn.MLP
    scaling: Scaling
    degree: int = eqx.field(static=True)

    def __init__(self, n_in: int, n_out: int, scaling: Scaling, *, degree: int = 2,
                 width: int = 12, depth: int = 2, key, init_scale: float = 1e-2):
        if degree < 0:
            raise ValueError(f"the polynomial degree must be at least 0, not {degree}")
        mlp = eqx.nn.MLP(n_in - 1, n_out * (degree + 1), width, depth,
                         activation=jax.nn.sigmoid, key=key)
        self.mlp = _small_last_layer(mlp, init_scale)
        self.scaling = scaling
        self.degree = degree

    def coefficients(self, y_features):
        """The heads N_0..N_degree at the (unscaled) state features: (degree + 1, n_out)."""
        s = self.scaling
        x = (y_features - s.z_mean[:-1]) / s.z_scale[:-1]
        return self.mlp(x).reshape(self.degree + 1, -1)

    def __call__(self, z):
        s = self.scaling
        p = (z[-1] - s.z_mean[-1]) / s.z_scale[-1]
        powers = p ** jnp.arange(self.degree + 1)
        return s.out_scale * (powers @ self.coefficients(z[:-1]))


def feature_scaling(Z: np.ndarray, F: np.ndarray) -> Scaling:
    """Input standardisation from the training features, output scale from target forces."""
    Z = np.asarray(Z)
    scale = Z.std(axis=0)
    scale = np.where(scale > 1e-12 * (1 + np.abs(Z.mean(axis=0))), scale, 1.0)
    out = np.sqrt(np.mean(np.asarray(F) ** 2, axis=0))
    out = np.where(out > 0, out, 1.0)
    return Scaling(jnp.asarray(Z.mean(axis=0)), jnp.asarray(scale), jnp.asarray(out))



class RestFreeCorrection(eqx.Module):
    """A correction that cannot move the equilibrium at rest, and changes its linearisation
    only through a few explicit linear terms:

        U(y; p) = N(y; p) - N(0; p) - J_y N(0; p) y - out_scale * (L0 + L1 s) (y / y_scale),

    with N the inner network (MLPCorrection or PolynomialParamCorrection), s the standardised
    parameter and (L0, L1) two (n_dof, 2 n_dof) matrices: a linear force on the
    displacements and velocities, affine in the parameter (damping, stiffness and their
    coupling, each changing linearly with the airspeed). The network carries only the
    nonlinear part; where the equilibrium loses stability (the Hopf point) is decided by the
    mechanistic model and the explicit linear terms, which the orbits near the Hopf point
    identify and which extrapolate to rest as a straight line in the airspeed, instead of
    by the network's extrapolation to rest, where no orbit was measured.

    Rest is y = 0: the mechanistic aerofoil's equilibrium (no force at rest), which the
    correction therefore keeps.
    """
    inner: eqx.Module
    linear: jax.Array             # (2, n_dof, 2 n_dof): L0, L1
    n_dof: int = eqx.field(static=True)

    def __init__(self, inner: eqx.Module, n_dof: int, linear=None):
        self.inner = inner
        self.n_dof = n_dof
        self.linear = (jnp.zeros((2, n_dof, 2 * n_dof)) if linear is None
                       else jnp.asarray(linear))

    @property
    def scaling(self) -> Scaling:
        return self.inner.scaling

    @property
    def mlp(self) -> eqx.nn.MLP:
        return self.inner.mlp

    def linear_matrix(self, p):
        """The explicit linear terms' matrix at the (unscaled) parameter p, in force per
        state unit: the correction's Jacobian in y at rest."""
        s = self.scaling
        ps = (p - s.z_mean[-1]) / s.z_scale[-1]
        n = 2 * self.n_dof
        return -(s.out_scale[:, None] * (self.linear[0] + self.linear[1] * ps)
                 / s.z_scale[None, :n])

    def _rest_terms(self, p):
        """What is subtracted at the parameter p: the network's value at rest and the
        matrix (its Jacobian in y at rest less the explicit linear terms)."""
        rest = jnp.zeros_like(self.scaling.z_mean).at[-1].set(p)
        f0 = self.inner(rest)
        n = 2 * self.n_dof
        jac = jax.jacfwd(lambda y: self.inner(jnp.concatenate([y, rest[n:]])))(rest[:n])
        return f0, jac - self.linear_matrix(p)

    def __call__(self, z):
        rest = z.at[:-1].set(0.0)
        # one forward-mode pass: the network at rest and its derivative along y
        f0, df = jax.jvp(self.inner, (rest,), (z.at[-1].set(0.0),))
        return self.inner(z) - f0 - df + self.linear_matrix(z[-1]) @ z[:-1]

    def at_parameter(self, p) -> "RestFreeAtParameter":
        """The same correction with the parameter fixed at p, its rest terms computed
        once: an orbit's integration calls the correction at one airspeed hundreds of
        times, and the terms at rest are most of each call's cost."""
        return RestFreeAtParameter(self.inner, *self._rest_terms(p))


class RestFreeAtParameter(eqx.Module):
    """A :class:`RestFreeCorrection` at one parameter value (the one its rest terms were
    computed at; the features' parameter must be that value)."""
    inner: eqx.Module
    offset: jax.Array              # N(0; p)
    matrix: jax.Array              # J_y N(0; p) - L(p)

    @property
    def scaling(self) -> Scaling:
        return self.inner.scaling

    def __call__(self, z):
        return self.inner(z) - self.offset - self.matrix @ z[:-1]
