"""The oscillator's truth: the S-curve of forced orbits at a fixed frequency."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..oscillator import OscillatorParams
from .continuation import _continue, _crossings, _fixed_parameter_solve, _locate_fold, _Point
from .shooting import _OscillatorProblem, compiled_plugin, effect_vector, first_harmonic

# --------------------------------------------------------------------------------------
# oscillator: S-curve at fixed frequency
# --------------------------------------------------------------------------------------

@dataclass
class ForcedCurve:
    """Forced periodic orbits of the oscillator against base-acceleration amplitude Phi
    (m/s^2) at a fixed forcing frequency, in continuation order.

    Arrays: Phi, amp (first-harmonic displacement amplitude, m), x_max (max |x|, m),
    current_amp (first-harmonic coil current amplitude, A), floquet_max (largest
    multiplier modulus), stable, states (state (x, x', i) at t = 0, when the forcing
    Phi cos(w t) peaks). ``folds``: dicts (Phi, amp, floquet_max, state, index: the
    curve point just before the fold), each located to solver precision.
    """

    freq_hz: float
    Phi: np.ndarray
    amp: np.ndarray
    x_max: np.ndarray
    current_amp: np.ndarray
    floquet_max: np.ndarray
    stable: np.ndarray
    states: np.ndarray
    folds: list
    params: OscillatorParams
    effects: np.ndarray
    n_steps: int
    scales: np.ndarray
    termination: str = ""
    _problem: object = field(default=None, repr=False, compare=False)


def _oscillator_record(problem: _OscillatorProblem, pt: _Point) -> dict:
    u = pt.us * problem.su
    fmax = float(np.max(np.abs(problem.floquet(pt.J))))
    return dict(Phi=float(u[3]), amp=first_harmonic(pt.H[:, 0])[0],
                x_max=float(np.max(np.abs(pt.H[:, 0]))),
                current_amp=first_harmonic(pt.H[:, 2])[0],
                floquet_max=fmax, stable=bool(fmax < 1.0), state=u[:3].copy())


def oscillator_scurve(freq_hz: float, params: OscillatorParams = OscillatorParams(),
                      effects=None, *, Phi_start: float = 0.1, Phi_max: float | None = None,
                      amp_max: float = 0.05, n_steps: int = 600, ds_max: float = 0.25,
                      max_points: int = 800, plugin=None) -> ForcedCurve:
    """Continue the forced periodic orbits at ``freq_hz`` in the forcing amplitude Phi.

    Starts at Phi_start (m/s^2) from rest as the Newton guess (nearly linear there),
    then pseudo-arclength continuation over the 3-state system (x, x', coil current)
    with the period fixed at 1/f, through any folds, until Phi exceeds Phi_max
    (default: the shaker limit), Phi turns negative, the amplitude exceeds amp_max (m)
    or max_points orbits are traced. Scaled unknowns: x by 1 mm, x' by w x 1 mm,
    current by the linear coil response to 1 mm, Phi by 5 m/s^2. A user ``plugin`` force
    (the rig's ``--effect-plugin`` callable returning (F,) in N, time-invariant and
    compilable, see :func:`compiled_plugin`) is integrated with the rest; it must vanish
    at rest (the continuation starts from rest).
    """
    E = effect_vector("oscillator", effects)
    if Phi_max is None:
        Phi_max = params.shaker_limit
    omega = 2.0 * np.pi * freq_hz
    sx = 1e-3
    si = params.theta * omega * sx / math.hypot(params.R, omega * params.L)
    su = np.array([sx, omega * sx, si, 5.0])
    force = None if plugin is None else compiled_plugin(plugin, ndof=1)
    problem = _OscillatorProblem(params, E, freq_hz, n_steps, su, force)
    first = _fixed_parameter_solve(problem, np.zeros(4), Phi_start / su[3])
    if first is None:
        raise RuntimeError(f"oscillator_scurve: no orbit at Phi = {Phi_start} ({freq_hz} Hz)")
    t0 = np.zeros(4)
    t0[3] = 1.0

    def stop(us):
        u = us * su
        if u[3] > Phi_max:
            return "Phi above Phi_max"
        if u[3] < 0:
            return "Phi below zero"
        if abs(u[0]) > amp_max:
            return "amplitude above amp_max"
        return ""

    tr = _continue(problem, first, t0, ds=0.05, ds_min=1e-7, ds_max=ds_max,
                   max_points=max_points, stop=stop)
    recs = [_oscillator_record(problem, pt) for pt in tr.points]
    folds = []
    for k in tr.folds:
        rec = _oscillator_record(problem, _locate_fold(problem, tr, k))
        folds.append(dict(Phi=rec["Phi"], amp=rec["amp"], floquet_max=rec["floquet_max"],
                          index=k, state=rec["state"]))

    def col(name, dtype=float):
        return np.array([r[name] for r in recs], dtype=dtype)

    return ForcedCurve(
        freq_hz=float(freq_hz), Phi=col("Phi"), amp=col("amp"), x_max=col("x_max"),
        current_amp=col("current_amp"), floquet_max=col("floquet_max"),
        stable=col("stable", bool), states=np.array([r["state"] for r in recs]),
        folds=folds, params=params, effects=E, n_steps=n_steps, scales=su,
        termination=tr.reason, _problem=problem)


def oscillator_orbit_at(Phi: float, curve: ForcedCurve) -> list[dict]:
    """Every orbit of ``curve`` at forcing amplitude Phi, re-solved by Newton at exactly
    Phi, sorted by amplitude. Each entry: amp, x_max, current_amp, floquet_max, stable,
    state."""
    problem = curve._problem
    out = []
    for k in _crossings(curve.Phi, Phi):
        P0, P1 = curve.Phi[k], curve.Phi[k + 1]
        w = 0.0 if P1 == P0 else (Phi - P0) / (P1 - P0)
        u = np.append((1 - w) * curve.states[k] + w * curve.states[k + 1], Phi)
        pt = _fixed_parameter_solve(problem, u / problem.su, Phi / problem.su[3])
        if pt is None:
            raise RuntimeError(f"oscillator_orbit_at: Newton failed at Phi = {Phi}")
        out.append(_oscillator_record(problem, pt))
    out.sort(key=lambda r: r["amp"])
    return out


def oscillator_amplitude_at(Phi: float, curve: ForcedCurve) -> list[tuple[float, bool]]:
    """[(first-harmonic amplitude in m, stable), ...] of all branches at Phi, smallest
    first (three entries between the folds of an S-curve, one outside)."""
    return [(r["amp"], r["stable"]) for r in oscillator_orbit_at(Phi, curve)]
