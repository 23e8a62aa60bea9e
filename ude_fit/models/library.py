"""The candidate effects: physically named terms a mechanistic model may be missing.

One description serves three users, so a term is written once:

* the explainer evaluates an effect's columns on the samples of the measured orbits
  (numpy) and regresses the residual on them;
* identification of a refined model uses the same columns next to the mechanistic
  model's own regressors (least squares, equation error);
* the refined model (``_refine.Refined``) evaluates the same formula inside its vector
  field (jax.numpy), so what was selected is exactly what is simulated and traced.

A term's formula takes ``xp`` (numpy or jax.numpy), a mapping ``S`` of the sample
states (aerofoil: h, al, hd, ad, V; oscillator: x, xd, w = forcing angular
frequency) and the effect's shape parameter (a freeplay half-width, a lag time
constant) and returns its columns stacked on the last axis. Each column enters its
equation as ``+ coefficient * column`` on the right-hand side (a generalised force,
per unit mass for the oscillator), so a spring that is missing shows a negative
coefficient. Dissipative effects (friction, nonlinear damping) must come out negative
and a freeplay's removed spring positive: a candidate whose fit has the other sign
is not that physics, whatever it does for the residual, and is not admitted.

An effect with *hidden* states is structural: linear dynamics driven by the states
(a first-order lag ``tau z' + z = x``; the aerofoil's wake lag in R. T. Jones's
two-pole form) feeding columns back. On a periodic orbit its columns come from the
hidden states' steady periodic solution (exact by Fourier series); in the refined
model the hidden states are states of their own.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .._fourier import K
from .forms import EQUATIONS, form_columns, parse_located_key, state_label, state_parts
from .mechanistic import model_class


HEAVE_FRICTION_VS = 1e-3     # m/s: smoothing of sign(h') (tanh); below the orbits' speeds
PITCH_FRICTION_VS = 1e-2     # rad/s
TIP_FRICTION_VS = 1e-3       # m/s (oscillator)

# what an effect is, for the report: catalogue structural nonlinearities are what the
# loop is meant to find; the others describe linear or parameter-dependent mismatch
STRUCTURAL = "structural nonlinearity"
LINEAR = "linear term (a retuned mechanistic parameter)"
AERO = "parameter-dependent linear term (unsteady aerodynamics)"
HIDDEN = "hidden state (first-order lag)"
FREQ = "frequency-dependent linear term"


@dataclass(frozen=True)
class Hidden:
    """Linear hidden dynamics an effect brings: states ``z`` (``n`` of them) with
    ``z' = rate(xp, S, z, shape)``, feeding ``output(xp, S, z, shape)`` (the effect's
    columns) back; ``states(S, shape)`` is their steady periodic solution along each
    measured orbit (numpy, (N, n)), exact by Fourier series because the dynamics are
    linear in z."""
    n: int
    states: object
    rate: object
    output: object


@dataclass(frozen=True)
class Effect:
    key: str                          # short name for the command line (--add KEY)
    name: str                         # what a person calls it
    equation: int                     # 0: heave (or the oscillator's equation), 1: pitch
    terms: tuple[str, ...]            # formulas of the columns, as printed
    formula: object                   # (xp, S, shape) -> (..., len(terms)); None if hidden
    kind: str = STRUCTURAL
    shape_name: str = ""              # "" when the effect has no shape parameter
    grid: object = None               # (S) -> tuple of shape values to try
    hidden: Hidden | None = None      # hidden states (lags), or None
    sign: int = 0                     # physical sign of the coefficient (-1: dissipative
                                      # or opposing; +1: a spring removed); 0: either

    @property
    def n_hidden(self) -> int:
        return self.hidden.n if self.hidden else 0

    @property
    def lag(self) -> bool:
        return self.hidden is not None


def _per_orbit_filter(S, x: np.ndarray, transfer) -> np.ndarray:
    """Steady periodic output of a linear filter along each orbit: harmonic k of ``x``
    times ``transfer(s, orbit_index_arrays)`` at s = i k w."""
    n = int(S["n"])
    X = np.fft.rfft(np.asarray(x, float).reshape(-1, n), axis=1)
    s = 1j * np.arange(X.shape[1])[None, :] * np.asarray(S["w"]).reshape(-1, n)[:, :1]
    return np.fft.irfft(X * transfer(s), n=n, axis=1).ravel()


def lag(S, x: np.ndarray, tau: float) -> np.ndarray:
    """z with tau z' + z = x along each periodic orbit (its steady periodic solution):
    harmonic k of x divided by 1 + i k w tau. ``S["n"]`` samples per orbit, uniform in
    phase; ``S["w"]`` the orbit's angular frequency at each sample. This is how a hidden
    first-order state (an aerodynamic lag, a coil current) shows on a periodic orbit."""
    return _per_orbit_filter(S, x, lambda s: 1.0 / (1.0 + s * tau))


def first_order_lag(inputs, m: int) -> Hidden:
    """``m`` lag states tau z' = x - z of the inputs ``x = inputs(xp, S)``; the columns
    are the states themselves."""
    def states(S, tau):
        X = np.asarray(inputs(np, S), float).reshape(len(S["w"]), -1)
        return np.stack([lag(S, X[:, j], tau) for j in range(m)], 1)
    return Hidden(m, states, lambda xp, S, z, tau: (inputs(xp, S) - z) / tau,
                  lambda xp, S, z, tau: z)


# R. T. Jones's two-pole approximation of the Wagner function (Theodorsen's C(k) ~
# 1 - 0.165 k/(k - 0.0455 i) - 0.335 k/(k - 0.3 i)): a textbook form, not fitted
JONES = {"c1": 0.165, "c2": 0.0455, "c3": 0.335, "c4": 0.3}


def _downwash(xp, S):
    """The aerofoil's three-quarter-chord downwash over b: what drives the wake lag."""
    return S["hd"] / S["b"] + (0.5 - S["a"]) * S["ad"] + S["V"] * S["al"] / S["b"]


def _jones_states(S, _):
    c2, c4 = JONES["c2"], JONES["c4"]
    p = (np.asarray(S["V"]) / S["b"]).reshape(-1, int(S["n"]))[:, :1]
    den = lambda s: s ** 2 + s * (c2 + c4) * p + c2 * c4 * p ** 2
    u = _downwash(np, S)
    return np.stack([_per_orbit_filter(S, u, lambda s: 1.0 / den(s)),
                     _per_orbit_filter(S, u, lambda s: s / den(s))], 1)


def _jones_rate(xp, S, z, _):
    c2, c4 = JONES["c2"], JONES["c4"]
    p = S["V"] / S["b"]
    return xp.stack([z[..., 1], _downwash(xp, S) - (c2 + c4) * p * z[..., 1]
                     - c2 * c4 * p ** 2 * z[..., 0]], -1)


def _jones_output(xp, S, z, _):
    V = S["V"]
    return xp.stack([V ** 2 * z[..., 1], V ** 3 * z[..., 0], V * S["hd"], V * S["ad"],
                     V ** 2 * S["al"]], -1)


JONES_AERO = Hidden(2, _jones_states, _jones_rate, _jones_output)
JONES_TERMS = ("V^2 w'", "V^3 w", "V h'", "V alpha'", "V^2 alpha")


def columns(effect: Effect, S, shape) -> np.ndarray:
    """The effect's columns on the samples ``S`` (numpy, (N, len(terms))), band-limited
    to the harmonics the measured orbits carry (:func:`band_limited`)."""
    if effect.hidden:
        X = np.asarray(effect.hidden.output(np, S, effect.hidden.states(S, shape), shape),
                       float)
    else:
        X = np.asarray(effect.formula(np, S, shape), float)
    X = X.reshape(X.shape[0], -1)
    return band_limited(X, int(S["n"]))


def band_limited(X: np.ndarray, n: int, K: int = K) -> np.ndarray:
    """Columns X (N, m), orbit-major with ``n`` samples per orbit, with every harmonic
    above K removed orbit by orbit. The measured orbits are K-harmonic averages, so
    the residual holds harmonics 0..K only; a column compared with it must be too
    (sign(h') and sat(alpha) otherwise carry a Gibbs tail the residual cannot show)."""
    F = np.fft.rfft(X.reshape(-1, n, X.shape[-1]), axis=1)
    F[:, K + 1:] = 0.0
    return np.fft.irfft(F, n=n, axis=1).reshape(X.shape)


def _sat(xp, x, d):
    return xp.clip(x, -d, d)


def _stack(xp, *cols):
    return xp.stack(cols, -1)


def _fraction_grid(key: str, fractions):
    def grid(S):
        top = float(np.max(np.abs(S[key]))) or 1.0
        return tuple(float(f) * top for f in fractions)
    return grid


def _tau_grid(S):
    period = 2 * np.pi / float(np.median(S["w"]))
    return tuple(float(x) for x in period * np.array([0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0,
                                                      2.0]))


def _aero_lag_inputs(xp, S):
    return _stack(xp, S["V"] * S["hd"], S["V"] ** 2 * S["al"])


def _dissipation(prefix, what, where, eq, v, label, vs, vs_label) -> tuple:
    """Cubic and quadratic damping and Coulomb friction of the velocity ``S[v]``: each
    must take energy out (negative coefficient)."""
    return (
        Effect(f"{prefix}cubic_damping", f"cubic {what}damping", eq, (f"{label}^3",),
               lambda xp, S, d: _stack(xp, S[v] ** 3), sign=-1),
        Effect(f"{prefix}quadratic_damping", f"quadratic {what}damping", eq,
               (f"|{label}| {label}",),
               lambda xp, S, d: _stack(xp, xp.abs(S[v]) * S[v]), sign=-1),
        Effect(f"{prefix}friction", f"Coulomb friction{where}", eq,
               (f"tanh({label}/{vs_label})",),
               lambda xp, S, d: _stack(xp, xp.tanh(S[v] / vs)), sign=-1),
    )


def _aerodynamics(dof, eq, x, v, label) -> tuple:
    """Linear, airspeed-dependent candidates of one equation: what a quasi-steady model
    gets wrong about the flow (the unsteady aerodynamics)."""
    return (
        Effect(f"{dof}_airspeed", f"airspeed-dependent {dof} terms", eq,
               (f"V {label}", f"V^2 {label}", f"V {label}'"),
               lambda xp, S, d: _stack(xp, S["V"] * S[x], S["V"] ** 2 * S[x], S["V"] * S[v]),
               AERO),
        Effect(f"{dof}_aero_lag", f"aerodynamic lag state in {dof}", eq,
               ("lag_tau(V h')", "lag_tau(V^2 alpha)"), None, AERO, "tau (s)", _tau_grid,
               first_order_lag(_aero_lag_inputs, 2)),
        Effect(f"{dof}_unsteady_aero", f"unsteady aerodynamics in {dof} (Jones wake lag)",
               eq, JONES_TERMS, None, AERO, hidden=JONES_AERO),
    )


_FREEPLAY_FRACTIONS = (0.02, 0.05, 0.1, 0.15, 0.2, 0.3, 0.4, 0.5)


FLUTTER_EFFECTS = (
    Effect("heave_cubic", "cubic heave stiffness", 0, ("h^3",),
           lambda xp, S, d: _stack(xp, S["h"] ** 3)),
    Effect("heave_poly57", "heave stiffness, 5th and 7th order", 0, ("h^5", "h^7"),
           lambda xp, S, d: _stack(xp, S["h"] ** 5, S["h"] ** 7)),
    Effect("heave_quadratic", "quadratic heave stiffness", 0, ("h^2",),
           lambda xp, S, d: _stack(xp, S["h"] ** 2)),
    *_dissipation("heave_", "heave ", " in heave", 0, "hd", "h'", HEAVE_FRICTION_VS, "1e-3 m/s"),
    Effect("heave_pitch_coupling", "pitch coupling in heave", 0, ("alpha", "h alpha"),
           lambda xp, S, d: _stack(xp, S["al"], S["h"] * S["al"]), LINEAR),
    *_aerodynamics("heave", 0, "h", "hd", "h"),
    Effect("pitch_freeplay", "pitch freeplay", 1, ("sat(alpha, delta)",),
           lambda xp, S, d: _stack(xp, _sat(xp, S["al"], d)),
           STRUCTURAL, "delta (rad)", _fraction_grid("al", _FREEPLAY_FRACTIONS), sign=1),
    Effect("pitch_poly57", "pitch stiffness, 5th and 7th order", 1, ("alpha^5", "alpha^7"),
           lambda xp, S, d: _stack(xp, S["al"] ** 5, S["al"] ** 7)),
    *_dissipation("pitch_", "pitch ", " in pitch", 1, "ad", "alpha'", PITCH_FRICTION_VS,
                  "1e-2 rad/s"),
    Effect("pitch_heave_coupling", "heave coupling in pitch", 1, ("h", "h alpha"),
           lambda xp, S, d: _stack(xp, S["h"], S["h"] * S["al"]), LINEAR),
    *_aerodynamics("pitch", 1, "al", "ad", "alpha"),
)

OSCILLATOR_EFFECTS = (
    Effect("freeplay", "freeplay (dead zone) in the spring", 0, ("sat(x, delta)",),
           lambda xp, S, d: _stack(xp, _sat(xp, S["x"], d)),
           STRUCTURAL, "delta (m)", _fraction_grid("x", _FREEPLAY_FRACTIONS), sign=1),
    Effect("quadratic_stiffness", "quadratic stiffness", 0, ("x^2",),
           lambda xp, S, d: _stack(xp, S["x"] ** 2)),
    *_dissipation("", "", "", 0, "xd", "x'", TIP_FRICTION_VS, "1e-3 m/s"),
    Effect("frequency_linear", "forcing-frequency-dependent stiffness and damping", 0,
           ("w x", "w^2 x", "w x'"),
           lambda xp, S, d: _stack(xp, S["w"] * S["x"], S["w"] ** 2 * S["x"],
                                   S["w"] * S["xd"]), FREQ),
    Effect("velocity_lag", "first-order lag state driven by velocity (e.g. a coil current)",
           0, ("lag_tau(x')",), None, HIDDEN, "tau (s)", _tau_grid,
           first_order_lag(lambda xp, S: _stack(xp, S["xd"]), 1)),
    # (a lag of the displacement is not a separate candidate: with x in the model,
    # lag(x') = (x - lag(x)) / tau spans the same columns)
)

LIBRARY = {"flutter": FLUTTER_EFFECTS, "oscillator": OSCILLATOR_EFFECTS}


def effect(system: str, key: str) -> Effect:
    """The library's effect called ``key``, or a located shape's generic form
    (``heave.h.above``, see ``forms``); ValueError naming the known ones otherwise."""
    for e in LIBRARY[system]:
        if e.key == key:
            return e
    located = located_effect(system, key)
    if located is not None:
        return located
    raise ValueError(f"unknown effect {key!r} for the {system} model "
                     f"(known: {', '.join(e.key for e in LIBRARY[system])})")


def effect_choice(system: str, key: str, shape: float | None = None, *,
                  flag: str = "--add", spec: str | None = None) -> tuple[str, float | None]:
    """An effect to add to the mechanistic model, checked: ``(key, shape or None)`` (None:
    the shape is chosen from the data, by cross-validation). ValueError (one line, naming
    ``flag``) for an unknown effect, a shape on an effect without one, or a shape that is
    not a positive number."""
    e = effect(system, key)
    if shape is not None:
        where = f"{flag} {spec or f'{key}={shape}'}"
        if not e.shape_name:
            raise ValueError(f"{where}: {e.key} has no shape parameter")
        if isinstance(shape, bool) or not isinstance(shape, (int, float)) \
                or not np.isfinite(shape) or shape <= 0:
            raise ValueError(f"{where}: the {e.shape_name} must be positive")
        shape = float(shape)
    return e.key, shape


def parse_effects(system: str, specs, *, flag: str = "--add") -> tuple:
    """``["heave_cubic", "pitch_freeplay=0.01"]`` -> ((key, shape or None), ...), each
    checked by :func:`effect_choice`; an effect named twice is a ValueError too."""
    out = []
    for spec in specs:
        key, sep, val = str(spec).partition("=")
        shape = None
        if sep:
            if not effect(system, key.strip()).shape_name:
                raise ValueError(f"{flag} {spec}: {key.strip()} has no shape parameter")
            try:
                shape = float(val)
            except ValueError:
                raise ValueError(f"{flag} {spec}: {val!r} is not a number") from None
        pair = effect_choice(system, key.strip(), shape, flag=flag, spec=str(spec))
        if any(k == pair[0] for k, _ in out):
            raise ValueError(f"{flag} {pair[0]} given twice")
        out.append(pair)
    return tuple(out)


def located_effect(system: str, key: str) -> Effect | None:
    """The generic form of a located shape as an effect (None if ``key`` is not one): a
    class of ``forms`` in one equation with one state as argument."""
    parsed = parse_located_key(system, key)
    if parsed is None:
        return None
    equation, key_state, f = parsed
    state, times = state_parts(key_state)
    name = state_label(system, state)
    label = state_label(system, key_state)
    factor = "" if times is None else " " + state_label(system, times)
    return Effect(key, f"{f.label} in {label} ({EQUATIONS[system][equation]} equation)",
                  equation, tuple(t.replace("u", name).replace("c", f"({name}/d)") + factor
                                  for t in f.terms),
                  lambda xp, S, d: form_columns(xp, f, S, key_state, d), STRUCTURAL,
                  "d" if f.thresholds else "",
                  (lambda S: f.thresholds(np.asarray(S[state], float))) if f.thresholds
                  else None)


def states_of(data, system: str) -> dict:
    """The mapping S of the formulas on every sample of a TrainingData (``data.ys`` may
    carry hidden states after (q, q'); they are ignored)."""
    return sample_states(system, np.asarray(data.ys), np.asarray(data.drive.param),
                         np.asarray(data.drive.omega))


def sample_states(system: str, ys: np.ndarray, param: np.ndarray, omega: np.ndarray) -> dict:
    """The mapping S of the formulas from sampled orbits ys (n_orbits, n, >= n_state)."""
    n_o, n, _ = ys.shape
    rep = lambda a: np.repeat(np.asarray(a, float), n)
    S = model_class(system).sample_states(ys.reshape(n_o * n, -1), rep(param))
    S["w"] = rep(omega)
    S["n"] = n
    return S
