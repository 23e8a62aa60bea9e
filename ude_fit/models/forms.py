"""Generic shape classes a dynamicist names, as few-parameter terms of one state.

A located shape (``discovery.locate``) is described by fitting each class's form to it
(``discovery.describe``); the winning form, placed in its equation with its state as
argument, is a refined mechanistic term like a catalogue effect (``library.Effect``):
the same formula serves the regression (numpy) and the refined model's vector field
(jax.numpy). Nothing here is fitted to a case: the classes are the textbook list
(hardening/softening, asymmetry, a kink, a one-sided stop or contact, a symmetric dead
zone or saturation, a smooth saturation), each in every equation and every state, and
a form's threshold ``d`` is chosen by the data on a grid of the state's own quantiles.

Each column enters ``+ c * column`` on the right-hand side (a generalised force), so a
restoring term has ``c < 0``; the phrase a class gives depends on the sign and on whether
its state is a displacement, a velocity or the bifurcation parameter.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

DISPLACEMENT, VELOCITY, PARAMETER = "displacement", "velocity", "parameter"

# the sample states each system's formulas read (library.sample_states): the name a
# report uses and what the state is
STATES = {"flutter": {"h": ("h", DISPLACEMENT), "al": ("alpha", DISPLACEMENT),
                      "hd": ("h_dot", VELOCITY), "ad": ("alpha_dot", VELOCITY),
                      "V": ("V", PARAMETER)},
          "oscillator": {"x": ("x", DISPLACEMENT), "xd": ("x_dot", VELOCITY),
                         "w": ("omega", PARAMETER)}}
EQUATIONS = {"flutter": ("heave", "pitch"), "oscillator": ("x",)}
# each equation's own velocity: a damping whose coefficient depends on a displacement
# (position-dependent damping, c(h) h') is a shape of that displacement times it
OWN_VELOCITY = {"flutter": ("hd", "ad"), "oscillator": ("xd",)}


def state_parts(key: str) -> tuple[str, str | None]:
    """``"h"`` -> ("h", None); ``"h*hd"`` (a coefficient of h multiplying h') -> ("h", "hd")."""
    state, _, times = key.partition("*")
    return state, times or None


def state_label(system: str, key: str) -> str:
    """The name a report uses: ``h``, or ``h_dot(h)`` for a damping of h' depending on h."""
    state, times = state_parts(key)
    name = STATES[system][state][0]
    return name if times is None else f"{STATES[system][times][0]}({name})"


def located_states(system: str, equation: int) -> dict:
    """{key: label} the locator fits shapes of in one equation: every state alone, and
    every displacement as the coefficient of the equation's own velocity."""
    out = {k: v[0] for k, v in STATES[system].items()}
    own = OWN_VELOCITY[system][equation]
    for k, (_, role) in STATES[system].items():
        if role == DISPLACEMENT:
            out[f"{k}*{own}"] = state_label(system, f"{k}*{own}")
    return out


def form_columns(xp, f, S, key: str, d):
    """A form's columns for a located state key (times the velocity it multiplies)."""
    state, times = state_parts(key)
    X = f.formula(xp, S[state], d)
    return X if times is None else X * S[times][..., None]


def _words(role: str, c: float) -> tuple[str, str]:
    """(what a negative-going term is, what a positive one is) for a state's role."""
    if role == VELOCITY:
        return ("damping", "negative damping") if c < 0 else ("negative damping", "damping")
    return ("stiffening", "softening") if c < 0 else ("softening", "stiffening")


@dataclass(frozen=True)
class Form:
    key: str
    label: str                     # the class, as a person calls it
    formula: object                # (xp, u, d) -> (..., m)
    n_terms: int = 1
    thresholds: object = None      # (u samples) -> grid of d; None: no threshold
    terms: tuple = ()              # printed with the state's name for "u"

    @property
    def n_parameters(self) -> int:
        return self.n_terms + (1 if self.thresholds else 0)

    def region(self, name: str, d) -> dict:
        return {name: [None, None]}

    def phrase(self, name: str, role: str, c: float, d) -> str:
        return f"{self.label} in {name}"


def _quantile_grid(lo_q, hi_q, n=12):
    return lambda u: tuple(float(x) for x in np.quantile(u, np.linspace(lo_q, hi_q, n)))


def _abs_grid(u):
    top = float(np.max(np.abs(u))) or 1.0
    return tuple(float(f) * top for f in np.linspace(0.05, 0.9, 12))


class _Cubic(Form):
    def phrase(self, name, role, c, d):
        if role == VELOCITY:
            what = ("amplitude-dependent (cubic) damping" if c < 0
                    else "amplitude-dependent negative damping")
            return f"{what} in {name}"
        return f"{'hardening' if c < 0 else 'softening'} (cubic) in {name}"


class _Quadratic(Form):
    def phrase(self, name, role, c, d):
        return f"asymmetry (quadratic) in {name}"


class _Kink(Form):
    def region(self, name, d):
        return {name: [0.0, None]}

    def phrase(self, name, role, c, d):
        more = _words(role, c)[0]
        kind = ("direction-dependent damping" if role == VELOCITY
                else "asymmetric (bilinear) stiffness")
        return f"{kind}: {more} for {name} > 0"


class _Above(Form):
    def region(self, name, d):
        return {name: [d, None]}

    def phrase(self, name, role, c, d):
        if role == DISPLACEMENT and c < 0:
            return f"one-sided stop or contact: stiffening for {name} > {d:.4g}"
        return f"one-sided {_words(role, c)[0]} for {name} > {d:.4g}"


class _Below(Form):
    def region(self, name, d):
        return {name: [None, d]}

    def phrase(self, name, role, c, d):
        # the column is negative where it acts: c > 0 opposes a negative state
        if role == DISPLACEMENT and c > 0:
            return f"one-sided stop or contact: stiffening for {name} < {d:.4g}"
        return f"one-sided {_words(role, -c)[0]} for {name} < {d:.4g}"


class _Beyond(Form):
    def region(self, name, d):
        return {f"|{name}|": [d, None]}

    def phrase(self, name, role, c, d):
        if role == DISPLACEMENT:
            what = ("dead zone (freeplay-like): stiffer beyond" if c < 0
                    else "saturation: softer beyond")
            return f"{what} |{name}| = {d:.4g}"
        return f"{_words(role, c)[0]} beyond |{name}| = {d:.4g}"


class _Tanh(Form):
    def phrase(self, name, role, c, d):
        if role == VELOCITY and c < 0:
            return f"friction-like (smooth sign) damping in {name}, scale {d:.4g}"
        return f"smooth saturation in {name}, scale {d:.4g}"


FORMS = (
    _Cubic("cubic", "cubic", lambda xp, u, d: u[..., None] ** 3, terms=("u^3",)),
    _Quadratic("quadratic", "quadratic", lambda xp, u, d: (u ** 2)[..., None],
               terms=("u^2",)),
    _Kink("kink", "kink at zero", lambda xp, u, d: xp.maximum(u, 0.0)[..., None],
          terms=("max(u, 0)",)),
    _Above("above", "one-sided, above d", lambda xp, u, d: xp.maximum(u - d, 0.0)[..., None],
           thresholds=_quantile_grid(0.5, 0.95), terms=("max(u - d, 0)",)),
    _Below("below", "one-sided, below d", lambda xp, u, d: xp.minimum(u - d, 0.0)[..., None],
           thresholds=_quantile_grid(0.05, 0.5), terms=("min(u - d, 0)",)),
    _Beyond("beyond", "symmetric, beyond |d|",
            lambda xp, u, d: (u - xp.clip(u, -d, d))[..., None],
            thresholds=_abs_grid, terms=("u - sat(u, d)",)),
    _Tanh("tanh", "smooth saturation", lambda xp, u, d: xp.tanh(u / d)[..., None],
          thresholds=_abs_grid, terms=("tanh(u/d)",)),
)


class _Spline(Form):
    """No class: the shape itself, a cubic regression spline of the state scaled by its
    largest size on the data (``d``), held constant beyond it (a term never extrapolates
    a cubic), with knots at fixed fractions: the located shape carried into the model."""

    def phrase(self, name, role, c, d):
        return f"a shape of {name} (regression spline)"


SPLINE_KNOTS = tuple(float(k) for k in np.linspace(-1.0, 1.0, 9)[1:-1])


def _spline_columns(xp, u, d):
    c = xp.clip(u / d, -1.0, 1.0)
    return xp.stack([c ** 2, c ** 3] + [xp.maximum(c - k, 0.0) ** 3 for k in SPLINE_KNOTS], -1)


SPLINE = _Spline("spline", "regression spline (no class)", _spline_columns,
                 n_terms=2 + len(SPLINE_KNOTS),
                 thresholds=lambda u: (float(np.max(np.abs(u))) or 1.0,),
                 terms=("c^2", "c^3") + tuple(f"max(c - {k:.2f}, 0)^3" for k in SPLINE_KNOTS))


def form(key: str) -> Form:
    if key == SPLINE.key:
        return SPLINE
    for f in FORMS:
        if f.key == key:
            return f
    raise ValueError(f"unknown shape class {key!r} (known: {', '.join(f.key for f in FORMS)})")


def located_key(system: str, equation: int, state: str, form_key: str) -> str:
    """The effect key of a form in an equation and a state, e.g. ``heave.h.above``, or
    ``heave.h_dot(h).quadratic`` for a damping of h' whose coefficient is quadratic in h."""
    return f"{EQUATIONS[system][equation]}.{state_label(system, state)}.{form_key}"


def parse_located_key(system: str, key: str):
    """(equation, state key, Form) of a located key, or None if ``key`` is not one."""
    parts = key.split(".")
    if len(parts) != 3 or parts[0] not in EQUATIONS[system]:
        return None
    equation = EQUATIONS[system].index(parts[0])
    by_name = {v: k for k, v in located_states(system, equation).items()}
    if parts[1] not in by_name or parts[2] not in {f.key for f in FORMS + (SPLINE,)}:
        return None
    return equation, by_name[parts[1]], form(parts[2])
