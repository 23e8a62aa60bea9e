"""An orbit's series solved for a model (*variable projection*): the coefficients that
minimise the misfit to the measured samples plus the weighted defect as the model's orbit,
by Gauss-Newton steps, so that a collocated objective need not carry the series as unknowns
of its own (:class:`.collocation.SolvedSeries`).

Free series are thousands of numbers, and trained beside the network they lag it: on noisy
simulated campaigns that path ended, from every start, in a basin with twice shooting's loss
and the Hopf point 0.13 m/s low, although the collocated objective itself prefers shooting's
answer (docs/experiments.md, fifty-seventh session). Solved, they do not lag.

The Gauss-Newton matrix is the misfit's (constant) and the defect's, which along the phases
is the series' derivative against itself, against the linearised field and the field's own
Gram matrix; the last two are sums over the phases of two basis functions against the
Jacobian's entries, formed from their Fourier transforms (:class:`.fourier.Products`).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from .fourier import Basis

# Gauss-Newton steps that solve an orbit's series from the measured samples' series at
# every evaluation: the problem is least squares, linear in the series but for the vector
# field along it, and on the simulated aerofoil's orbits the second step leaves the
# objective within 0.3 % of its converged value from the first training step on
SERIES_STEPS = 2
# the fractions of a Gauss-Newton step tried, longest first
BACKTRACK = jnp.asarray([1.0, 0.5, 0.25, 0.125])


class OrbitResiduals(eqx.Module):
    """One orbit's misfit and defect as weighted residual vectors of its series, whose
    squared norms are the objective's ``fit`` and ``defect`` terms."""
    frozen: object          # the model at the orbit's drive (UDE.at_drive)
    drive: object
    basis: Basis
    ys: jax.Array           # (n, states) the measured samples
    T: jax.Array
    fit_scale: jax.Array    # (states,) the misfit residual's factor per state
    defect_scale: jax.Array  # (states,) the defect residual's

    @staticmethod
    def of(frozen, drive, basis: Basis, ys, T, sw, y_scale) -> "OrbitResiduals":
        n, m = basis.samples.shape[0], basis.fine.shape[0]
        omega = 2.0 * jnp.pi / T
        # fit = mean over samples and states of the weighted squared misfit;
        # defect = (2 pi)^2 sum over states of the phases' mean squared mismatch
        fit_scale = jnp.sqrt(sw / (jnp.mean(sw) * n * ys.shape[1])) / y_scale
        defect_scale = 2.0 * jnp.pi / (omega * y_scale * jnp.sqrt(m))
        return OrbitResiduals(frozen, drive, basis, ys, T, fit_scale, defect_scale)

    def field(self, C):
        """The vector field and its Jacobian at the series' fine phases."""
        m = self.basis.fine.shape[0]

        def f(t, yy):
            v = self.frozen.vector_field(t, yy, self.drive)
            return v, v
        return jax.vmap(jax.jacfwd(f, argnums=1, has_aux=True))(
            self.T * jnp.arange(m) / m, self.basis.fine @ C)

    def misfit(self, C):
        return (self.basis.samples @ C - self.ys) * self.fit_scale

    def defect(self, C, f):
        omega = 2.0 * jnp.pi / self.T
        return (omega * (self.basis.fine_slope @ C) - f) * self.defect_scale

    def objective(self, C, weight):
        """misfit + weight * defect, the sum of squares the series minimises."""
        m = self.basis.fine.shape[0]
        f = jax.vmap(lambda t, yy: self.frozen.vector_field(t, yy, self.drive))(
            self.T * jnp.arange(m) / m, self.basis.fine @ C)
        return jnp.sum(self.misfit(C) ** 2) + weight * jnp.sum(self.defect(C, f) ** 2)

    def normal_equations(self, C, weight):
        """The Gauss-Newton matrix and gradient of misfit + weight * defect at the series
        ``C`` (2k+1, states), over its coefficients flattened coefficient-major: the
        residuals' Jacobian A as A^T A and A^T r."""
        K, S = C.shape
        J, f = self.field(C)                    # (m, S, S), (m, S)
        omega = 2.0 * jnp.pi / self.T
        c2 = self.defect_scale ** 2
        products = self.basis.products
        # the defect's normal matrix over (coefficient, state) pairs: the series'
        # derivative against itself, against the linearised field (X and its transpose),
        # and the field's Gram matrix along the phases
        slope_gram = self.basis.fine_slope.T @ self.basis.fine_slope
        X = omega * jnp.transpose(products.slopes(c2[None, :, None] * J), (2, 0, 3, 1))
        field_gram = products.values(jnp.einsum("ist,s,isu->itu", J, c2, J))
        H_def = (omega ** 2 * jnp.einsum("kl,tu->ktlu", slope_gram, jnp.diag(c2))
                 - X - jnp.transpose(X, (2, 3, 0, 1))
                 + jnp.transpose(field_gram, (2, 0, 3, 1)))
        H_fit = jnp.einsum("kl,tu->ktlu", self.basis.samples.T @ self.basis.samples,
                           jnp.diag(self.fit_scale ** 2))
        r_def = self.defect(C, f) * self.defect_scale
        g = (self.basis.samples.T @ (self.misfit(C) * self.fit_scale)
             + weight * (omega * self.basis.fine_slope.T @ r_def
                         - self.basis.fine.T @ jnp.einsum("ist,is->it", J, r_def)))
        return (H_fit + weight * H_def).reshape(K * S, K * S), g.reshape(-1)

    def gauss_newton_step(self, C, weight):
        """One Gauss-Newton step on misfit + weight * defect over the series ``C``, cut back
        (:data:`BACKTRACK`) until it lowers the sum, or none: far from the model's orbit
        the vector field's curvature can make the full step overshoot."""
        H, g = self.normal_equations(C, weight)
        step = jnp.linalg.solve(H, g).reshape(C.shape)
        now = self.objective(C, weight)
        tries = C - BACKTRACK[:, None, None] * step
        lower = jax.vmap(lambda c: self.objective(c, weight))(tries) < now
        # the longest step that lowers the sum (NaN lowers nothing), else none
        return jnp.where(lower.any(), tries[jnp.argmax(lower)], C)


def solve(res: OrbitResiduals, C, weight):
    """The series that minimises the orbit's misfit plus ``weight`` times its defect for
    this model: :data:`SERIES_STEPS` Gauss-Newton steps from ``C``, outside the gradient
    (at the minimum the series' own change moves the objective by nothing to first order,
    so the model's gradient is the objective's at fixed series)."""
    C = jax.lax.fori_loop(0, SERIES_STEPS, lambda _, c: res.gauss_newton_step(c, weight), C)
    return jax.lax.stop_gradient(C)
