"""Two routes to the missing physics, and whether they agree.

The *residual route* locates and names what the least-squares mechanistic model leaves on
the measured orbits (``locate`` + ``describe``, ``explain``). The *UDE route* asks the same
two questions of a UDE's learnt correction U, evaluated on the same samples: U is what the
network found it had to add so that the model's orbits pass through the data, so where it
acts (equation, state) should be where the residual says the model is short. Both routes go
through the same locator and describer, so a difference is a difference in what the two
fits saw, not in how they were read.

Agreement is on *where* (the equation and state of each route's strongest significant
shape; both finding nothing beyond the noise agrees too). The catalogue's top-ranked term
on each side is reported beside it: two routes may place an effect alike and name it
differently when the shape sits between two classes.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import numpy as np

from ..models.forms import EQUATIONS
from ..models.library import states_of
from ..models.ude import UDE
from ..training.identify import TrainingData, augment
from .describe import describe
from .explain import Explanation, explain
from .locate import Location, locate


def learnt_correction(model: UDE, data: TrainingData) -> np.ndarray:
    """The UDE's correction force on every sample of ``data``, (N, n_equations): the
    generalised force it adds to the mechanistic model's right-hand side."""
    if model.correction is None:
        raise ValueError("the model has no learnt correction")
    d2 = augment(data, model.mech)
    per_sample = jax.vmap(jax.vmap(model.correction_force, in_axes=(0, None)),
                          in_axes=(0, 0))
    U = np.asarray(per_sample(d2.ys, d2.drive))
    return U.reshape(-1, U.shape[-1])


@dataclass(frozen=True)
class RouteFinding:
    """What one route found: the strongest located shape and the catalogue's top term."""
    route: str                        # "residual" or "UDE correction"
    equation: str | None              # None: no shape beats the noise
    state: str | None
    description: str | None           # the describer's phrase for the shape
    catalogue_key: str | None         # top-ranked catalogue effect (None: none significant)
    catalogue_name: str | None

    def __post_init__(self):
        if (self.equation is None) != (self.state is None):
            raise ValueError("a located shape has both an equation and a state, or neither")

    @classmethod
    def of(cls, route: str, location: Location, explanation: Explanation) -> "RouteFinding":
        sig = location.significant()
        top = explanation.top() if explanation.significant else None
        eq = state = phrase = None
        if sig:
            s = sig[0]
            eq = EQUATIONS[location.system][s.equation]
            state = s.name
            phrase = s.description.phrase() if s.description is not None else None
        return cls(route, eq, state, phrase, None if top is None else top["key"],
                   None if top is None else top["name"])

    @property
    def where(self) -> tuple:
        return (self.equation, self.state)

    def sentence(self) -> str:
        where = ("no shape of a single state beats the noise" if self.equation is None
                 else f"an effect in {self.equation} depending on {self.state}"
                 + (f" ({self.description})" if self.description else ""))
        named = ("no catalogue term significant" if self.catalogue_key is None
                 else f"catalogue's top term {self.catalogue_name} ({self.catalogue_key})")
        return f"{self.route}: {where}; {named}"

    def to_json(self) -> dict:
        return {"route": self.route, "equation": self.equation, "state": self.state,
                "description": self.description, "catalogue_key": self.catalogue_key,
                "catalogue_name": self.catalogue_name}


@dataclass(frozen=True)
class RouteComparison:
    residual: RouteFinding
    ude: RouteFinding

    @property
    def agree(self) -> bool:
        """Same equation and state (or both nothing beyond the noise)."""
        return self.residual.where == self.ude.where

    @property
    def same_name(self) -> bool:
        return self.residual.catalogue_key == self.ude.catalogue_key

    def sentence(self) -> str:
        if self.agree:
            head = ("The residual route and the UDE route agree: "
                    + ("neither finds a shape beyond the noise" if self.residual.equation
                       is None else f"both locate an effect in {self.residual.equation} "
                       f"depending on {self.residual.state}"))
        else:
            head = "The residual route and the UDE route disagree on where the effect acts"
        tail = ("; the catalogue's top terms are the same" if self.same_name else
                "; the catalogue's top terms differ")
        return head + tail + "."

    def to_json(self) -> dict:
        return {"agree": self.agree, "same_catalogue_term": self.same_name,
                "summary": self.sentence(), "residual": self.residual.to_json(),
                "ude": self.ude.to_json()}


def _route(name: str, data: TrainingData, system: str, *, seed: int, bootstrap: int,
           target=None, location: Location | None = None,
           explanation: Explanation | None = None) -> RouteFinding:
    if location is None:
        location = describe(locate(data, system, seed=seed, target=target),
                            states_of(data, system))
    if explanation is None:
        explanation = explain(data, system, seed=seed, bootstrap=bootstrap, target=target)
    return RouteFinding.of(name, location, explanation)


def compare_routes(data: TrainingData, system: str, model: UDE, *, seed: int = 0,
                   bootstrap: int = 200, residual_location: Location | None = None,
                   residual_explanation: Explanation | None = None) -> RouteComparison:
    """Locate and name the mechanistic residual and ``model``'s learnt correction on the
    same samples; ``model`` is a UDE on the least-squares mechanistic model of ``data``.
    A residual route the caller already has (the loop's first step) is reused."""
    residual = _route("residual", data, system, seed=seed, bootstrap=bootstrap,
                      location=residual_location, explanation=residual_explanation)
    ude = _route("UDE correction", data, system, seed=seed, bootstrap=bootstrap,
                 target=learnt_correction(model, data))
    return RouteComparison(residual, ude)
