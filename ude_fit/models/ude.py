"""The UDE: a mechanistic model plus an optional correction U(features(y, drive)), and its
vector field (the one every integrator and the continuation use)."""

from __future__ import annotations


import equinox as eqx
import jax.numpy as jnp

from .mechanistic import Drive, MechanisticModel


class UDE(eqx.Module):
    """Mechanistic model plus an optional correction U(features(y, drive))."""
    mech: MechanisticModel
    correction: eqx.Module | None = None

    @property
    def system(self) -> str:
        return self.mech.system

    @property
    def n_hidden(self) -> int:
        """Hidden states of a refined mechanistic model (lags), after (q, q')."""
        return self.mech.n_hidden

    @property
    def n_state(self) -> int:
        return 2 * self.mech.n_dof + self.n_hidden

    def features(self, y, drive: Drive):
        # the measured states and the model's parameter feature (airspeed, or forcing
        # frequency); hidden states are the model's own and stay out
        y = y[:2 * self.mech.n_dof]
        return jnp.concatenate([y, self.mech.parameter_feature(drive)[None]])

    def correction_force(self, y, drive: Drive):
        if self.correction is None:
            return jnp.zeros(self.mech.n_dof)
        return self.correction(self.features(y, drive))

    def vector_field(self, t, y, drive: Drive):
        n = self.mech.n_dof
        q, qd = y[:n], y[n:2 * n]
        if self.n_hidden:
            z = y[2 * n:]
            F = self.mech.force(q, qd, drive, z)
        else:
            F = self.mech.force(q, qd, drive)
        F = F + self.correction_force(y, drive)
        qdd = self.mech.accelerations(F, t, drive)
        if self.n_hidden:
            return jnp.concatenate([qd, qdd, self.mech.hidden_rate(q, qd, drive, z)])
        return jnp.concatenate([qd, qdd])

    def at_drive(self, drive: Drive) -> "UDE":
        """The same vector field for one drive, with whatever the correction computes
        once per parameter value (``at_parameter``) done here, outside an integrator's
        loop. Exact: the parameter is a constant of each orbit."""
        freeze = getattr(self.correction, "at_parameter", None)
        if freeze is None:
            return self
        return UDE(self.mech, freeze(self.mech.parameter_feature(drive)))

    def with_correction(self, correction) -> "UDE":
        return UDE(self.mech, correction)

