"""A correction of the Hopf normal form's kind: linear terms, plus a damping that depends on
the oscillation's size alone.

    U(y) = L y  -  phi(e) C q',

with ``e(y)`` the squared size of the state (each displacement and velocity over its spread
in the data, squares averaged): near-constant along a harmonic orbit, since the velocities'
spread is the displacements' times the orbits' frequency. ``C`` is positive semi-definite
(learnt) and ``phi`` vanishes at rest, so the linearisation at rest is the mechanistic
model's plus the explicit linear terms (the Hopf point is theirs).

Why this form: along a closed orbit of near-constant ``e`` the damping term's work per
cycle is ``-phi(e)`` times a positive number. If the orbit's shape did not change with its
size, the rest of the model's work per cycle would be ``g(V)`` times the size plus terms
linear in it, and with ``phi`` convex (a free linear term plus softplus ramps with
non-negative slopes) the net growth would be concave in ``e``: at most two orbits per airspeed
and at most one fold. That is the design's premise, and it does not hold in general: the
damping itself turns the heave-pitch phase of a flutter mode, and the aerodynamic work
depends on that phase, so a random correction of this form traced on the nominal aerofoil
had four folds (docs/experiments.md, twelfth session). A free network bends its work per cycle as often as the
points' scatter asks, and each bend is a fold the physics does not have (docs/experiments.md:
8 to 16 folds on lee2020). An amplitude-dependent *stiffness* is left out on purpose: on a
flutter mode it moves the growth rate through the aerodynamic coupling, in whatever shape it
has, and with it the form had 10 folds on lee2020 (docs/experiments.md, twelfth session).

``phi`` is a one-input network of a fixed form: a linear term plus softplus ramps at knots
spread over the sizes the data holds (evenly in amplitude), each ramp's slope learnt and made
non-negative.

The linear terms: where the unstable orbits point at a Hopf point (their amplitude^2 line),
:func:`pin_hopf` sets one damping that puts the linearisation's loss of stability there and
holds it (:class:`RestLinear`); training may change the linear terms at every airspeed alike
(damping, stiffness, couplings: the mode's shape and frequency), and :func:`resolve` re-solves
the held damping after each change so that the Hopf point stays put. Trained free, the linear
terms moved the Hopf point far below every orbit (docs/experiments.md, twelfth session).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from scipy.optimize import brentq

from .corrections import Scaling
from .mechanistic import Drive


class SizeBasis(eqx.Module):
    """The fixed (untrained) part: knots and ramp widths for the size ``e``."""
    knots: jax.Array
    widths: jax.Array

    @staticmethod
    def spanning(e: np.ndarray, n_knots: int) -> "SizeBasis":
        """``n_knots`` knots from 0 to the largest size in the data, evenly spaced in the
        amplitude (the square root of the size, what a diagram shows), each ramp as wide
        as the gap to the next knot: as fine at small orbits as at large ones."""
        top = float(np.max(e)) if np.size(e) and np.max(e) > 0 else 1.0
        edges = top * (np.arange(n_knots + 1) / n_knots) ** 2
        return SizeBasis(jnp.asarray(edges[:-1]), jnp.asarray(np.diff(edges)))

    def ramps(self, e):
        """Softplus ramps at the knots, each zero at e = 0: (n_knots,)."""
        w = self.widths
        return w * (jax.nn.softplus((e - self.knots) / w) - jax.nn.softplus(-self.knots / w))


class RestLinear(eqx.Module):
    """The fixed part of the linear terms: L, (n_dof, 2 n_dof) in scaled units, set from the
    data before training (:func:`pin_hopf`), and the airspeed the Hopf point is held at
    while the trained part changes (None: not held)."""
    matrices: jax.Array
    v_hopf: float | None = eqx.field(static=True, default=None)


class AmplitudeCorrection(eqx.Module):
    """U(y) = L y - phi(e) C q' (module docstring), in scaled units: states over their
    spread, forces over the residual's RMS. L is the same at every airspeed: a trained slope
    in the airspeed moved the loss of stability below the held Hopf point."""
    rest: RestLinear         # L's fixed part, and where the Hopf point is held
    linear: jax.Array        # (n_dof, 2 n_dof): L's trained change
    phi_lin: jax.Array       # phi's free linear slope
    phi_raw: jax.Array       # (n_knots,) softplus -> phi's ramp slopes (>= 0)
    c_chol: jax.Array        # (n_dof, n_dof) lower triangle: C = R R^T
    scaling: Scaling
    basis: SizeBasis
    n_dof: int = eqx.field(static=True)

    def __init__(self, n_dof: int, scaling: Scaling, basis: SizeBasis, *, key,
                 init_scale: float = 1e-2):
        n, k = n_dof, int(basis.knots.shape[0])
        keys = jax.random.split(key, 4)
        r = lambda i, *shape: init_scale * jax.random.normal(keys[i], shape)
        self.rest = RestLinear(jnp.zeros((n, 2 * n)))
        self.linear = r(0, n, 2 * n)
        self.phi_lin = r(1)
        self.phi_raw = r(2, k) - 4.0            # ramps start nearly flat
        self.c_chol = jnp.eye(n) + r(3, n, n)
        self.scaling, self.basis, self.n_dof = scaling, basis, n_dof

    def size(self, y_scaled):
        """e: the mean square of the scaled displacements and velocities."""
        return jnp.mean(y_scaled[:2 * self.n_dof] ** 2)

    def phi(self, e):
        """The size's damping coefficient: convex in e, zero at rest."""
        return self.phi_lin * e + jax.nn.softplus(self.phi_raw) @ self.basis.ramps(e)

    def linear_matrix(self):
        """The correction's Jacobian in y at rest, in force per state unit."""
        s = self.scaling
        L = self.rest.matrices + self.linear
        return s.out_scale[:, None] * L / s.z_scale[None, :2 * self.n_dof]

    def damping_direction(self, z):
        """C q' (force units), C positive semi-definite: a symmetric rescaling D_v of the
        velocities, each over its spread and each force over its RMS, keeps R R^T PSD."""
        s, n = self.scaling, self.n_dof
        d_v = jnp.sqrt(s.out_scale / s.z_scale[n:2 * n])
        R = jnp.tril(self.c_chol)
        return d_v * (R @ (R.T @ (d_v * z[n:2 * n])))

    def size_of(self, z):
        """e at the (unscaled) features z."""
        n2 = 2 * self.n_dof
        return self.size(z[:n2] / self.scaling.z_scale[:n2])

    def __call__(self, z):
        y = z[:2 * self.n_dof]
        return (self.linear_matrix() @ y
                - self.phi(self.size_of(z)) * self.damping_direction(z))


def amplitude_correction(Z: np.ndarray, n_dof: int, scaling: Scaling, *, key,
                         n_knots: int = 8, init_scale: float = 1e-2) -> AmplitudeCorrection:
    """A fresh correction whose knots span the sizes of the training samples ``Z``."""
    ys = np.asarray(Z)[:, :2 * n_dof] / np.asarray(scaling.z_scale[:2 * n_dof])
    e = np.mean(ys ** 2, axis=1)
    return AmplitudeCorrection(n_dof, scaling, SizeBasis.spanning(e, n_knots), key=key,
                               init_scale=init_scale)


def pin_hopf(model, v_hopf: float, span: float = 1e3):
    """``model`` (a UDE with an amplitude correction) with the correction's linear terms set
    to one damping, equal on every coordinate in scaled units, that puts the equilibrium's
    loss of stability at ``v_hopf`` (the data's estimate): the one linear fact the
    unstable orbits measure. The model unchanged where no damping in [-span, span] does."""
    c = model.correction
    n = c.n_dof
    shape = _hopf_damping(n)
    y0 = jnp.zeros(model.n_state)

    def with_damping(d):
        rest = RestLinear(d * shape, float(v_hopf))
        return eqx.tree_at(lambda u: (u.correction.rest, u.correction.linear), model,
                           (rest, jnp.zeros_like(c.linear)))

    def growth(d):
        m = with_damping(d)
        J = jax.jacfwd(lambda y: m.vector_field(0.0, y, Drive.of(v_hopf)))(y0)
        return float(np.max(np.real(np.linalg.eigvals(np.asarray(J)))))

    grid = np.concatenate([-np.logspace(3, -3, 25) * span / 1e3, [0.0],
                           np.logspace(-3, 3, 25) * span / 1e3])
    g = np.array([growth(d) for d in grid])
    # the smallest damping change that brings the growth rate to zero
    cross = [k for k in range(len(grid) - 1) if np.sign(g[k]) != np.sign(g[k + 1])]
    if not cross:
        return model
    k = min(cross, key=lambda k: min(abs(grid[k]), abs(grid[k + 1])))
    return with_damping(brentq(growth, grid[k], grid[k + 1], xtol=1e-12))


def _hopf_damping(n_dof: int):
    """The direction of the held damping: equal on every velocity, in scaled units."""
    n = n_dof
    return jnp.zeros((n, 2 * n)).at[:, n:].set(-jnp.eye(n))


def _char_poly(A):
    """Coefficients (1, a1, ..., an) of det(lambda I - A), Faddeev-LeVerrier: smooth in A."""
    n = A.shape[0]
    coeffs, M = [jnp.asarray(1.0)], jnp.zeros_like(A)
    for k in range(1, n + 1):
        M = A @ M + coeffs[-1] * jnp.eye(n)
        coeffs.append(-jnp.trace(A @ M) / k)
    return jnp.stack(coeffs)


def hurwitz_hopf(A):
    """The (n-1)th Hurwitz determinant of A's characteristic polynomial: zero where a pair
    of eigenvalues sits on the imaginary axis (with the others off it), the Hopf condition
    as a smooth function of the matrix."""
    a = _char_poly(A)
    n = A.shape[0]
    coef = lambda k: a[k] if 0 <= k <= n else jnp.asarray(0.0)
    H = jnp.stack([jnp.stack([coef(2 * j - i) for j in range(1, n)]) for i in range(1, n)])
    return jnp.linalg.det(H)


def resolve(model, newton_steps: int = 6):
    """``model`` with its amplitude correction's linear terms made concrete: the fixed part
    plus the trained change, plus the one damping (along the pinned direction) that keeps
    the Hopf point at the held airspeed, by Newton's method from zero (the fixed part held
    it before any change). Differentiable: the trained change moves the damping with it.
    Any other model is returned as it is."""
    c = model.correction
    if not isinstance(c, AmplitudeCorrection):
        return model
    total = c.rest.matrices + c.linear
    D = _hopf_damping(c.n_dof)
    y0 = jnp.zeros(model.n_state)

    def with_matrices(L):
        return eqx.tree_at(lambda u: (u.correction.rest, u.correction.linear), model,
                           (RestLinear(L), jnp.zeros_like(c.linear)))

    def residual(d):
        m = with_matrices(total + d * D)
        J = jax.jacfwd(lambda y: m.vector_field(0.0, y, Drive.of(c.rest.v_hopf)))(y0)
        return hurwitz_hopf(J)

    def newton(d, _):
        return d - residual(d) / jax.grad(residual)(d), None

    if c.rest.v_hopf is None:
        return with_matrices(total)
    d, _ = jax.lax.scan(newton, jnp.asarray(0.0), None, length=newton_steps)
    return with_matrices(total + d * D)
