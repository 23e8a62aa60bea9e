"""Truncated Fourier series of an orbit over its phase: the maps from coefficients to
samples, values and derivatives (:class:`Basis`), and the sums over phases of products of
two basis functions against a sequence (:class:`Products`), which the normal matrix of a
series' least-squares problem is made of (:mod:`.projection`)."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

# phases per sample where the vector field is matched and its Jacobian taken: the variational
# integration's Runge-Kutta steps are two phases long (a step's midpoint is a phase of the
# grid), one step per sample
FINE = 2


def harmonics_of(n: int) -> int:
    """The harmonics an orbit of ``n`` samples per period carries: all below the Nyquist
    frequency (whose cosine alone the samples cannot tell from aliasing)."""
    return (n - 1) // 2


class Basis(eqx.Module):
    """Linear maps from an orbit's Fourier coefficients (``2k + 1`` per state, a0, a1..ak,
    b1..bk) to its samples at the ``n`` measured phases, and to its values and phase
    derivatives at ``FINE * n`` phases; and the analysis map from the samples back."""
    analysis: jax.Array     # (2k+1, n)
    samples: jax.Array      # (n, 2k+1)
    fine: jax.Array         # (FINE n, 2k+1)
    fine_slope: jax.Array   # (FINE n, 2k+1): d/dphi
    products: "Products"

    @staticmethod
    def of(n: int) -> "Basis":
        k = harmonics_of(n)
        j = np.arange(1, k + 1)

        def synth(phi):
            return np.concatenate([np.ones((phi.size, 1)), np.cos(np.outer(phi, j)),
                                   np.sin(np.outer(phi, j))], axis=1)

        def slope(phi):
            return np.concatenate([np.zeros((phi.size, 1)), -j * np.sin(np.outer(phi, j)),
                                   j * np.cos(np.outer(phi, j))], axis=1)

        phi = 2 * np.pi * np.arange(n) / n
        fine = 2 * np.pi * np.arange(FINE * n) / (FINE * n)
        analysis = np.concatenate([np.full((1, n), 1.0 / n), 2.0 / n * np.cos(np.outer(j, phi)),
                                   2.0 / n * np.sin(np.outer(j, phi))], axis=0)
        return Basis(jnp.asarray(analysis), jnp.asarray(synth(phi)),
                     jnp.asarray(synth(fine)), jnp.asarray(slope(fine)),
                     Products.of(k, FINE * n))

    def through(self, ys):
        """(..., 2k+1, states) the series through samples ``ys`` (..., n, states)."""
        return jnp.einsum("kn,...ns->...ks", self.analysis, ys)

    def at_start(self, C):
        """(..., states) the series' value at phase 0."""
        k = (self.analysis.shape[0] - 1) // 2
        return C[..., 0, :] + jnp.sum(C[..., 1:k + 1, :], axis=-2)


class Products(eqx.Module):
    """Sums over the fine phases of two basis functions times a sequence g,
    ``sum_i b_k(phi_i) b_l(phi_i) g_i``, from the sequence's discrete Fourier transform.
    Each basis function is Re(c exp(i h phi)) (the mean: c = 1, h = 0; cos(j phi):
    c = 1, h = j; sin(j phi): c = -i, h = j; their derivatives: i h c), so a product of
    two is half the real part of c_k c_l exp(i (h_k + h_l) phi) + c_k conj(c_l)
    exp(i (h_k - h_l) phi), and its sum against g one of g's Fourier coefficients: the
    Gauss-Newton matrix costs a transform and a gather instead of a product of
    (phases x coefficients) matrices."""
    at_sum: jax.Array       # (2k+1, 2k+1) int: g's coefficient at -(h_k + h_l) mod m
    at_difference: jax.Array
    value_sum: jax.Array    # (2k+1, 2k+1) complex: c_k c_l / 2, value times value
    value_difference: jax.Array
    slope_sum: jax.Array    # d_k c_l / 2, slope times value
    slope_difference: jax.Array

    @staticmethod
    def of(k: int, m: int) -> "Products":
        j = np.arange(1, k + 1)
        h = np.concatenate([[0], j, j])
        c = np.concatenate([[1.0], np.ones(k), np.full(k, -1j)])
        d = 1j * h * c
        return Products(
            jnp.asarray((-(h[:, None] + h[None, :])) % m),
            jnp.asarray((-(h[:, None] - h[None, :])) % m),
            jnp.asarray(np.outer(c, c) / 2), jnp.asarray(np.outer(c, c.conj()) / 2),
            jnp.asarray(np.outer(d, c) / 2), jnp.asarray(np.outer(d, c.conj()) / 2))

    def _sums(self, g, w_sum, w_difference):
        G = jnp.fft.fft(g, axis=0)       # (m, ...): sum_i g_i exp(-i q phi_i) at q
        return jnp.real(jnp.moveaxis(G[self.at_sum], (0, 1), (-2, -1)) * w_sum
                        + jnp.moveaxis(G[self.at_difference], (0, 1), (-2, -1))
                        * w_difference)

    def values(self, g):
        """(..., 2k+1, 2k+1) sum_i b_k b_l g_i for g of shape (m, ...)."""
        return self._sums(g, self.value_sum, self.value_difference)

    def slopes(self, g):
        """(..., 2k+1, 2k+1) sum_i b'_k b_l g_i."""
        return self._sums(g, self.slope_sum, self.slope_difference)
