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


class LargeSwingFeed(eqx.Module):
    """A heave force k scale relu((h / h0)^2 - 1)^2 h': nothing while the heave stays
    within h0, energy fed in beyond it (k > 0; k is the trained weight, of order one as a
    network's are). Orbits whose swing stays within h0 do not feel it; a large enough k
    turns the stable branch back above them (a second fold where the data is silent)."""
    k: jax.Array
    scale: float = eqx.field(static=True, default=200.0)
    h0: float = eqx.field(static=True, default=0.1)
    # the swing factor's ceiling, if any: a bounded feed, as a saturating network's is (an
    # orbit asked for far beyond h0 then grows within a period instead of blowing up)
    cap: float | None = eqx.field(static=True, default=None)

    def __call__(self, z):
        swing = jax.nn.relu((z[0] / self.h0) ** 2 - 1.0) ** 2
        if self.cap is not None:
            swing = jnp.minimum(swing, self.cap)
        return jnp.stack([self.k * self.scale * swing * z[2], 0.0 * z[4]])
