"""A member's agreement with its rig's truth, where the truth is known: the rig's own model
traced by continuation (:mod:`rig_sim.physics.truth`), with the member's undeclared effects.

The comparison is the one the campaign tests make. Aerofoil: each point's heave amplitude
against the truth orbit of the same stability at its airspeed. Oscillator: each point's
forcing against the truth S-curve's forcing at the measured amplitude (along an S-curve the
amplitude at a given forcing is ill-conditioned near the folds, the forcing at a given
amplitude is not). With process noise the truth is the noise-free model's; with a plugin
force no truth is computed.
"""

from __future__ import annotations

import numpy as np

from rig_sim.physics.truth import flutter_lco_at, flutter_lco_branch, oscillator_scurve


def _ok(points: list[dict]) -> list[dict]:
    return [p for p in points if p.get("status", "ok") == "ok"]


def _flutter(points: list[dict], effects) -> dict:
    # the branch is traced from the Hopf point (23.95 m/s on the clean rig) down and back up
    V_max = max(24.5, max(p["parameter"] for p in points) + 1.0)
    branch = flutter_lco_branch(effects=effects, V_max=V_max)
    errors, unmatched = [], 0
    for p in points:
        ref = flutter_lco_at(p["parameter"], branch)["stable" if p["stable"] else "unstable"]
        if ref is None:
            unmatched += 1              # the truth has no orbit of that stability there
        else:
            errors.append(abs(p["amplitude"] / ref - 1.0))
    return {"quantity": "heave amplitude at the airspeed", "errors": errors,
            "unmatched": unmatched}


def _oscillator(points: list[dict], effects) -> dict:
    errors, unmatched = [], 0
    for f in sorted({p["frequency"] for p in points}):
        curve = oscillator_scurve(f, effects=effects)
        single_valued = bool(np.all(np.diff(curve.amp) > 0))
        for p in (q for q in points if q["frequency"] == f):
            A = p["amplitude"]
            if not single_valued or not curve.amp[0] <= A <= curve.amp[-1]:
                unmatched += 1
                continue
            errors.append(abs(p["parameter"] / float(np.interp(A, curve.amp, curve.Phi)) - 1.0))
    return {"quantity": "forcing at the measured amplitude", "errors": errors,
            "unmatched": unmatched}


def truth_agreement(rig: str, rig_table: dict, points: list[dict]) -> dict:
    """{"known": bool, ...}: with the truth, the largest and median relative error over the
    points compared, how many were compared and how many had no truth orbit to match."""
    if rig_table.get("plugin"):
        return {"known": False, "why": "a plugin force: no truth is computed for it"}
    points = _ok(points)
    if not points:
        return {"known": False, "why": "no points"}
    effects = list(rig_table.get("effects") or []) or None
    try:
        found = (_flutter if rig == "flutter" else _oscillator)(points, effects)
    except (RuntimeError, ValueError) as exc:       # e.g. an effect that leaves no Hopf point
        return {"known": False, "why": f"truth not traced: {exc}"}
    errors = found.pop("errors")
    return {"known": True, **found, "compared": len(errors),
            "noise_free": not rig_table.get("noise"),
            "max_error": max(errors) if errors else None,
            "median_error": float(np.median(errors)) if errors else None}
