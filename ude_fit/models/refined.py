"""A mechanistic model with named effects added as physical terms with their own parameters.

``Refined(base, added)`` is a mechanistic model like the one it wraps (same mass, same
fitted parameters) whose generalised force gains ``sum coefficient * column`` for every
added effect (see ``_library``). An effect with hidden dynamics (a lag, the wake's
two states) brings states ``z`` placed after ``(q, q')`` in the state vector; the UDE,
the integrators and the continuation see a longer state and need nothing else.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .library import Effect, effect
from .mechanistic import MechanisticModel, parameters_of



class AddedEffect(eqx.Module):
    system: str = eqx.field(static=True)
    key: str = eqx.field(static=True)
    shape: float | None = eqx.field(static=True)
    coefficients: jax.Array

    @property
    def spec(self) -> Effect:
        return effect(self.system, self.key)

    def names(self) -> list[str]:
        return [f"{self.key}[{t}]" for t in self.spec.terms]


class Refined(MechanisticModel):
    """A mechanistic model (``base``) with named effects added (``added``): the same
    model to everything downstream, with more fitted parameters and maybe hidden states."""
    base_model: MechanisticModel
    added: tuple

    @property
    def base(self) -> MechanisticModel:
        return self.base_model

    @property
    def effects(self) -> tuple:
        return self.added

    @property
    def system(self) -> str:
        return self.base_model.system

    @property
    def n_dof(self) -> int:
        return self.base_model.n_dof

    @property
    def autonomous(self) -> bool:
        return self.base_model.autonomous

    @property
    def n_hidden(self) -> int:
        return sum(a.spec.n_hidden for a in self.added)

    @property
    def known(self):
        return self.base_model.known

    @property
    def fitted(self):
        return tuple(self.base_model.fitted) + tuple(n for a in self.added for n in a.names())

    @property
    def must_be_positive(self):
        return self.base_model.must_be_positive

    @property
    def holds_secondary_tests(self) -> bool:
        return self.base_model.holds_secondary_tests

    def parameter_feature(self, drive):
        return self.base_model.parameter_feature(drive)

    def accelerations(self, F, t, drive):
        return self.base_model.accelerations(F, t, drive)

    def residual_force(self, qdd, F, t, drive):
        return self.base_model.residual_force(qdd, F, t, drive)

    def unphysical(self) -> str:
        return self.base_model.unphysical()

    def parameters(self) -> dict:
        out = parameters_of(self.base_model)
        for a in self.added:
            out.update(zip(a.names(), np.asarray(a.coefficients).tolist()))
        return out

    def values(self) -> dict:
        return self.parameters()

    def mass(self, param):
        return self.base_model.mass(param)

    def _hidden_slices(self):
        off = 0
        for a in self.added:
            n = a.spec.n_hidden
            yield a, slice(off, off + n)
            off += n

    def force(self, q, qd, drive, z=None):
        F = self.base_model.force(q, qd, drive)
        S = self.base_model.library_states(q, qd, drive)
        for a, sl in self._hidden_slices():
            e = a.spec
            if e.hidden:
                cols = e.hidden.output(jnp, S, z[sl], a.shape)
            else:
                cols = e.formula(jnp, S, a.shape)
            F = F.at[e.equation].add(jnp.dot(a.coefficients, cols))
        return F

    def hidden_rate(self, q, qd, drive, z):
        S = self.base_model.library_states(q, qd, drive)
        rates = [a.spec.hidden.rate(jnp, S, z[sl], a.shape)
                 for a, sl in self._hidden_slices() if a.spec.hidden]
        return jnp.concatenate(rates) if rates else jnp.zeros(0)

    def hidden_states(self, S: dict) -> np.ndarray:
        """The hidden states' steady periodic solution on the sampled orbits S (N, n)."""
        Z = [a.spec.hidden.states(S, a.shape) for a in self.added if a.spec.hidden]
        return np.concatenate(Z, 1) if Z else np.zeros((len(S["w"]), 0))

    def hidden_scales(self, S: dict) -> np.ndarray:
        """Typical sizes of the hidden states on samples S (for scaled continuation)."""
        s = np.sqrt(np.mean(self.hidden_states(S) ** 2, axis=0))
        return np.where(s > 0, s, 1.0)


def describe(mech) -> list[dict]:
    """The added effects of a (possibly) refined model, JSON-able."""
    return [{"key": a.key, "name": a.spec.name, "equation": a.spec.equation,
             "terms": list(a.spec.terms), "shape": a.shape, "shape_name": a.spec.shape_name,
             "coefficients": np.asarray(a.coefficients).tolist()} for a in mech.effects]


def refined(base, added: list[dict]) -> Refined:
    """Build from ``[{"key", "shape", "coefficients"}, ...]`` (as :func:`describe` gives)."""
    return Refined(base, tuple(
        AddedEffect(base.system, d["key"], None if d.get("shape") is None else float(d["shape"]),
                    jnp.asarray(np.asarray(d["coefficients"], float)))
        for d in added))
