"""What is a located shape? Each generic class (``models.forms``) and each catalogue term
of the equation is fitted in the shape's place, the other shapes and the mechanistic and
nuisance columns kept; they are compared with the spline itself and with nothing by the
Bayesian information criterion, the samples of an orbit counted as the 2K+1 numbers they
carry. The best is named with the evidence (the criterion of each contender); a catalogue
term wins a tie, having a name already, and the tied class of the other origin is kept
beside it (``Description.tie``) for the loop to try on the diagram. When the spline beats every class by a margin
Kass and Raftery call very strong (10), no class describes the shape: "an effect in
<equation> depending on <state>, shaped like <the best class>".
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..models.forms import (FORMS, SPLINE, STATES, VELOCITY, form_columns, located_key,
                            state_parts)
from ..models.library import LIBRARY, STRUCTURAL, band_limited, columns
from .locate import EquationLocation, Location, Shape, _solve_normal

VERY_STRONG = 10.0     # BIC differences (Kass and Raftery, 1995)
POSITIVE = 2.0


@dataclass
class Contender:
    key: str               # effect key (catalogue) or located key (heave.h.above)
    label: str
    catalogue: bool
    n_parameters: float
    shape: float | None
    coefficients: list
    bic: float
    rss: float

    def to_dict(self) -> dict:
        return {"key": self.key, "label": self.label, "catalogue": self.catalogue,
                "n_parameters": self.n_parameters, "shape": self.shape,
                "coefficients": self.coefficients, "bic": self.bic}


@dataclass
class Description:
    equation: str
    state: str
    role: str
    best: Contender                       # the class (or catalogue term) named
    spline: Contender | None              # the shape itself as a term (heave.h.spline)
    named: bool                           # False: no class fits as well as the spline
    phrase_text: str
    region: dict
    contenders: list = field(default_factory=list)   # by BIC, spline and none included
    # the best contender of the other origin (a class when a catalogue term is named, a
    # catalogue term when a class is) within positive BIC evidence of the best: the
    # criterion cannot tell them apart, so the loop lets the diagram decide
    tie: Contender | None = None

    def phrase(self) -> str:
        return self.phrase_text

    def to_dict(self) -> dict:
        return {"equation": self.equation, "state": self.state, "shape_class": self.best.label,
                "key": self.best.key, "named": self.named, "phrase": self.phrase_text,
                "region": self.region, "shape": self.best.shape,
                "coefficients": self.best.coefficients,
                "spline": None if self.spline is None else self.spline.to_dict(),
                "evidence": [c.to_dict() for c in self.contenders],
                "tie": None if self.tie is None else self.tie.to_dict()}


def _fit_with(design, yn, skip: int, C: np.ndarray):
    """RSS and the coefficients of C with C in the place of smooth ``skip``."""
    keep = design._keep(skip)
    X = np.concatenate([design.X[:, keep], C], 1)
    P = np.zeros((X.shape[1], X.shape[1]))
    P[:len(keep), :len(keep)] = design.penalty()[np.ix_(keep, keep)]
    b = _solve_normal(X.T @ X + P, X.T @ yn)
    r = yn - X @ b
    return float(r @ r), b[len(keep):]


def _bic(rss: float, n: int, n_eff: float, k: float) -> float:
    return float(n_eff * np.log(max(rss, 1e-300) / n) + k * np.log(n_eff))


def describe_shape(system: str, loc: EquationLocation, shape: Shape, S: dict) -> Description:
    design, yn, scale, _, n_eff = loc.design
    i = [s.key for s in design.smooths].index(shape.state)
    n = len(yn)
    state, times = state_parts(shape.state)
    u = np.asarray(S[state], float)
    name, role = STATES[system][state]
    if times is not None:
        # a coefficient of the equation's velocity depending on ``name``: a damping
        name, role = shape.name, VELOCITY
    eq_name = loc.name
    out = []

    def consider(key, label, catalogue, cols, k, d):
        norms = np.sqrt(np.mean(cols ** 2, 0))
        if not np.all(norms > 0):
            return None
        rss, c = _fit_with(design, yn, i, cols / norms)
        return Contender(key, label, catalogue, k, d, (c * scale / norms).tolist(),
                         _bic(rss, n, n_eff, k), rss)

    def best_over(grid, make):
        """The best threshold of one candidate: ``make(d)`` -> (key, label, catalogue,
        columns, k)."""
        found = [c for c in (consider(*make(d), d) for d in grid) if c is not None]
        if found:
            out.append(min(found, key=lambda c: c.bic))

    per_orbit = int(S["n"])
    for f in FORMS:
        best_over(f.thresholds(u) if f.thresholds else (None,), lambda d, f=f: (
            located_key(system, loc.equation, shape.state, f.key), f.label, False,
            band_limited(np.asarray(form_columns(np, f, S, shape.state, d), float), per_orbit),
            f.n_parameters))
    for e in LIBRARY[system]:
        if e.equation == loc.equation and e.kind == STRUCTURAL and e.formula is not None:
            best_over(e.grid(S) if e.grid else (None,), lambda d, e=e: (
                e.key, e.name, True, columns(e, S, d), len(e.terms) + (1 if e.grid else 0)))
    _, b = design.fit()
    rss_spline = float(np.sum((yn - design.X @ b) ** 2))
    spline = Contender("spline", "spline (no class)", False, shape.edf, None, [],
                       _bic(rss_spline, n, n_eff, shape.edf), rss_spline)
    keep, b0 = design.fit(skip=i)
    rss0 = float(np.sum((yn - design.X[:, keep] @ b0) ** 2))
    none = Contender("none", "nothing", False, 0, None, [], _bic(rss0, n, n_eff, 0), rss0)
    out.sort(key=lambda c: c.bic)
    # a catalogue term no worse than the best class by positive evidence, with no more
    # parameters, wins: it has a name already
    best = out[0]
    cat = next((c for c in out if c.catalogue), None)
    if cat is not None and cat.bic <= best.bic + POSITIVE and cat.n_parameters <= best.n_parameters:
        best = cat
    named = best.bic <= spline.bic + VERY_STRONG
    top = out[0].bic
    tie = next((c for c in out if c.catalogue != best.catalogue
                and c.bic <= top + POSITIVE), None)
    coef = best.coefficients[0] if best.coefficients else 0.0
    if best.catalogue:
        phrase = f"{best.label} (catalogue)"
        region = {name: [None, None]}
    else:
        f = next(f for f in FORMS if best.key.endswith("." + f.key))
        if times is None:
            phrase = f.phrase(name, role, coef, best.shape)
            region = f.region(name, best.shape)
        else:
            phrase = _damping_phrase(f, system, state, times, coef, best.shape)
            region = f.region(STATES[system][state][0], best.shape)
    if not named:
        phrase = f"an effect in {eq_name} depending on {name}, shaped like {phrase}"
        region = {name: shape.region.get(name)}
    contenders = sorted(out + [spline, none], key=lambda c: c.bic)
    cols = band_limited(np.asarray(form_columns(np, SPLINE, S, shape.state,
                                                SPLINE.thresholds(u)[0]), float), per_orbit)
    as_term = consider(located_key(system, loc.equation, shape.state, SPLINE.key),
                       SPLINE.label, False, cols, SPLINE.n_parameters, SPLINE.thresholds(u)[0])
    return Description(eq_name, name, role, best, as_term, named, phrase, region, contenders,
                       tie if named else None)


def _damping_phrase(f, system: str, state: str, times: str, c: float, d) -> str:
    """A damping of ``times`` whose coefficient is the form ``f`` of ``state``."""
    x, v = STATES[system][state][0], STATES[system][times][0]
    what = "damping" if c < 0 else "negative damping"
    if f.key == SPLINE.key:
        return f"{what} of {v} depending on {x} (regression spline)"
    term = f.terms[0].replace("u", x)
    if d is not None:
        term = term.replace("d", f"{d:.4g}")
    return f"{what} of {v} depending on {x}: coefficient ~ {term}"


def describe(location: Location, S: dict) -> Location:
    """Describe every significant shape of ``location`` (in place; returned)."""
    for loc in location.equations:
        for s in loc.significant:
            s.description = describe_shape(location.system, loc, s, S)
    return location


def _depends_on(system: str, key: str, shape, S: dict) -> list:
    """The states an effect's columns read (each state scaled in turn: do they change?)."""
    from ..models.library import effect
    e = effect(system, key)
    ref = columns(e, S, shape)
    out = []
    for k, (name, _) in STATES[system].items():
        moved = columns(e, {**S, k: 1.5 * np.asarray(S[k], float) + 0.1}, shape)
        if not np.allclose(moved, ref, rtol=1e-9, atol=1e-12):
            out.append(name)
    return out


def effect_fields(system: str, key: str, shape, coefficients, locations: list,
                  S: dict | None) -> dict:
    """What metrics.json's ``effect`` says beside name, terms and coefficients: the
    equation, the states it depends on, its shape class and the region where it acts."""
    from ..models.forms import EQUATIONS, parse_located_key
    from ..models.library import effect
    e = effect(system, key)
    out = {"equation": EQUATIONS[system][e.equation]}
    parsed = parse_located_key(system, key)
    if parsed is not None:
        _, key_state, f = parsed
        state, times = state_parts(key_state)
        name, role = STATES[system][state]
        c = float(coefficients[0]) if len(coefficients) else 0.0
        if times is None:
            out.update(states=[name], shape_class=f.label,
                       description=f.phrase(name, role, c, shape), region=f.region(name, shape))
        else:
            out.update(states=[name, STATES[system][times][0]],
                       shape_class=f"{f.label} (damping coefficient)",
                       description=_damping_phrase(f, system, state, times, c, shape),
                       region=f.region(name, shape))
        return out
    states = _depends_on(system, key, shape, S) if S is not None else []
    out.update(states=states, shape_class=e.kind, description=e.name,
               region={s: [None, None] for s in states})
    for loc in locations[:1]:
        for s in loc.significant():
            d = s.description
            if d is not None and d.best.key == key:
                out.update(description=d.phrase(), located_in=d.state)
    return out
