"""Hand-made corrections whose effect on the energy balance is known in closed form, for the
tests of the penalties and the training rounds."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp


class SpeedDamping(eqx.Module):
    """A heave force k (V - 20) h' (state z = h, alpha, h', alpha', V). It has no force or
    slope at rest beyond a damping of the flutter mode that grows with the airspeed; its work
    per cycle is k (V - 20) <h'^2>, so k < 0 takes energy out as the airspeed grows (the
    energy-rising condition broken) and k > 0 feeds it in."""
    k: jax.Array

    def __call__(self, z):
        return jnp.stack([self.k * (z[4] - 20.0) * z[2], 0.0 * z[4]])
