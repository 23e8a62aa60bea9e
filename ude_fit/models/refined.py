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
from .mechanistic import parameters_of



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


def _states(base, q, qd, drive) -> dict:
    if base.system == "flutter":
        return {"h": q[0], "al": q[1], "hd": qd[0], "ad": qd[1], "V": drive.param,
                "b": base.b, "a": base.a}
    return {"x": q[0], "xd": qd[0], "w": drive.omega}


class Refined(eqx.Module):
    base: eqx.Module
    added: tuple

    @property
    def system(self) -> str:
        return self.base.system

    @property
    def n_dof(self) -> int:
        return self.base.n_dof

    @property
    def n_hidden(self) -> int:
        return sum(a.spec.n_hidden for a in self.added)

    @property
    def known(self):
        return self.base.known

    @property
    def fitted(self):
        return tuple(self.base.fitted) + tuple(n for a in self.added for n in a.names())

    @property
    def g(self):
        return self.base.g

    def mass(self, param):
        return self.base.mass(param)

    def _hidden_slices(self):
        off = 0
        for a in self.added:
            n = a.spec.n_hidden
            yield a, slice(off, off + n)
            off += n

    def force(self, q, qd, drive, z=None):
        F = self.base.force(q, qd, drive)
        S = _states(self.base, q, qd, drive)
        for a, sl in self._hidden_slices():
            e = a.spec
            if e.hidden:
                cols = e.hidden.output(jnp, S, z[sl], a.shape)
            else:
                cols = e.formula(jnp, S, a.shape)
            F = F.at[e.equation].add(jnp.dot(a.coefficients, cols))
        return F

    def hidden_rate(self, q, qd, drive, z):
        S = _states(self.base, q, qd, drive)
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


def parameters_of_refined(mech: Refined) -> dict:
    out = parameters_of(mech.base)
    for a in mech.added:
        out.update(zip(a.names(), np.asarray(a.coefficients).tolist()))
    return out


def describe(mech) -> list[dict]:
    """The added effects of a (possibly) refined model, JSON-able."""
    if not isinstance(mech, Refined):
        return []
    return [{"key": a.key, "name": a.spec.name, "equation": a.spec.equation,
             "terms": list(a.spec.terms), "shape": a.shape, "shape_name": a.spec.shape_name,
             "coefficients": np.asarray(a.coefficients).tolist()} for a in mech.added]


def refined(base, added: list[dict]) -> Refined:
    """Build from ``[{"key", "shape", "coefficients"}, ...]`` (as :func:`describe` gives)."""
    return Refined(base, tuple(
        AddedEffect(base.system, d["key"], None if d.get("shape") is None else float(d["shape"]),
                    jnp.asarray(np.asarray(d["coefficients"], float)))
        for d in added))
