"""Measuring one point of the forced plan: Picard iteration, variance gate and record at a
target amplitude, a probe just below it, and riding out faults (re-arm, retry, skip)."""

from __future__ import annotations

import math
import time

import numpy as np

from ..harmonics import NH, amplitude
from ..messages import Arm, Configure, RigFault, RigRestarted, Settle
from ._steps import FAULTS, configure_and_settle, note, retry
from .forced_numbers import forcing_of, invasiveness, picard_update, record_fourier, zero_targets
from .options import ForcedOptions
from .scurve import Sweep


def probe(s: Sweep, o: ForcedOptions, res: dict, c2: float, prev: float):
    """Generator: the local slope just below a point whose label is in doubt (the
    probe stays above the target `prev` of the point below it). Returns
    {"slope", "slope_se", "method", "probe"} or None if the probe failed."""
    A = res["target"]
    sig = max(res["parameter_se"], 1e-12)
    eps = math.sqrt(2 * math.sqrt(2) * sig / max(abs(2 * c2), 1e-300)) if c2 else 0.5 * (A - prev)
    eps = min(max(eps, o.probe_min), 0.5 * (A - prev))
    Ap = round(A - eps, 7)
    if Ap <= prev or Ap <= 0:
        return None
    try:
        pr = yield from measure(s, o, Ap, start=res["harmonics"])
    except FAULTS as exc:
        yield note(f"f = {s.f:g} Hz: probe at {Ap * 1e3:.4f} mm lost ({exc})")
        yield from rearm(s, o, prev if prev > 0 else None)
        return None
    dA = res["amplitude"] - pr["amplitude"]
    if dA <= 0:
        return None
    slope = (res["parameter"] - pr["parameter"]) / dA
    se = math.hypot(res["parameter_se"], pr["parameter_se"]) / dA
    return {"slope": slope, "slope_se": se, "method": "probe secant",
            "probe": {"target": Ap, "amplitude": pr["amplitude"], "parameter": pr["parameter"],
                      "parameter_se": pr["parameter_se"], "noninvasive": pr["noninvasive"],
                      "rig_seconds": pr["rig_seconds"]}}


def attempt(s: Sweep, o: ForcedOptions, A: float, prev_A, start=None):
    """Generator: measure the point at target A, handling faults and restarts.
    Returns the measurement dict or None (skipped)."""
    faults = 0
    restarts = 0
    if not s.armed:
        if not (yield from rearm(s, o, prev_A)):
            return None
    while True:
        try:
            return (yield from measure(s, o, A, start=start))
        except RigRestarted:
            restarts += 1
            yield note(f"f = {s.f:g} Hz, A = {A * 1e3:.3f} mm: link lost; point repeated")
            if restarts > o.max_restarts or not (yield from rearm(s, o, None)):
                return None
        except RigFault as exc:
            faults += 1
            base = prev_A if prev_A is not None else 0.0
            new_A = round(base + 0.5 * (A - base), 6)
            if prev_A is None or faults > o.max_fault_retries or new_A - base < o.step_min:
                yield note(f"f = {s.f:g} Hz: {exc} at target A = {A * 1e3:.3f} mm; "
                           "target skipped")
                yield from rearm(s, o, prev_A)
                return None
            yield note(f"f = {s.f:g} Hz: {exc} at target A = {A * 1e3:.3f} mm; "
                       f"retrying at {new_A * 1e3:.3f} mm")
            A = new_A
            s.h = max(o.step_min, new_A - base)
            if not (yield from rearm(s, o, prev_A)):
                return None


def rearm(s: Sweep, o: ForcedOptions, back_to: float | None):
    """Generator: arm again after a fault or a reconnect; True once armed. With
    `back_to`, first on ``rearm_fraction`` of the target of that (last good) point
    (which may lie just under the trip level), ramped up from rest in
    ``rearm_ramp`` steps, waiting for the rig to settle there: a PD loop (damping
    ratio ~0.2 here) jumping from rest straight onto a large target overshoots it
    by half and can trip again. Three tries; after that `s.armed` stays False and the next
    point tries again before it measures anything."""
    s.armed = False

    def arm_once():
        # disarmed, the structure rings down on its own first (a trip latches
        # again while it still swings past the trip level: that is a retry);
        # the Configure also restarts the engine's period count for the Settle
        yield from configure_and_settle(zero_targets(), o.transient_periods)
        if back_to is None:
            yield Arm()
            return
        T = s.harm[-1][1] if s.harm else np.zeros(2 * NH + 1)
        n = max(o.rearm_ramp, 1)
        top = o.rearm_fraction * back_to
        yield Configure(s.settings(top / n, T / n))
        yield Arm()
        for k in range(2, n + 1):          # ramp up: a jump from rest overshoots
            yield Settle(periods=o.transient_periods)
            yield Configure(s.settings(top * k / n, T * k / n))
        yield Settle(periods=o.transient_periods + o.navg)

    if (yield from retry(arm_once, o.rearm_tries)):
        s.armed = True
        return True
    yield note(f"f = {s.f:g} Hz: the rig could not be re-armed ({o.rearm_tries} tries)")
    return False


def measure(s: Sweep, o: ForcedOptions, A: float, start=None):
    """Generator: Picard iteration, variance gate and record at target amplitude A.
    When the record's fit still finds the control invasive, Picard goes on from it
    (within ``max_picard`` iterations in all) and the point is recorded again."""
    navg = o.navg
    t_wall = time.time()
    T = s.predict_harmonics(A) if start is None else np.array(start, dtype=float)
    rows = []
    iters = 0
    rig_s = 0.0
    while True:
        est = None
        while iters < o.max_picard or est is None:
            est = yield from configure_and_settle(s.settings(A, T), o.transient_periods + navg)
            iters += 1
            rig_s += est.waited_s
            resid, fund, se = invasiveness(est.fourier["control"]["mean"],
                                           est.fourier["control"]["var"], navg)
            rows.append(_row(len(rows), "picard", A, est, resid, fund, se))
            if resid <= max(o.noninvasive_tol * fund, o.noninvasive_sigmas * se):
                break
            T = picard_update(T, est.fourier["control"]["mean"], est.fourier["response"]["mean"],
                              s.f, o, s.sample_rate)
        gate_ok = _gate(est, o)
        for _ in range(o.max_gate_polls):
            if gate_ok:
                break
            est = yield from configure_and_settle(s.settings(A, T), navg)
            rig_s += est.waited_s
            resid, fund, se = invasiveness(est.fourier["control"]["mean"],
                                           est.fourier["control"]["var"], navg)
            rows.append(_row(len(rows), "gate", A, est, resid, fund, se))
            gate_ok = _gate(est, o)
        if o.record_s > 0:        # the estimate read after it covers its last navg periods
            est = yield Settle(periods=0, record_s=o.record_s)
            rig_s += est.waited_s
            gate_ok = _gate(est, o)
        resid, fund, se = invasiveness(est.fourier["control"]["mean"],
                                       est.fourier["control"]["var"], navg)
        phi, sphi = forcing_of(est.fourier["excitation"]["mean"], est.fourier["excitation"]["var"],
                               navg)
        amp = amplitude(est.fourier["response"]["mean"])
        fit = record_fourier(est.samples, o.forcing_amplitude)
        source = "board"
        if fit is not None:
            source = "record"
            amp = amplitude(fit["response"]["mean"])
            phi = forcing_of(fit["excitation"]["mean"])[0]
            # its standard error from the fit's residual (the board's per-period spread
            # also holds the last of the transient and would overstate it)
            sphi = forcing_of(fit["excitation"]["mean"], fit["excitation"]["var_of_mean"])[1]
            resid, fund, se = invasiveness(fit["control"]["mean"], fit["control"]["var_of_mean"])
        rows.append(_row(len(rows), "record", A, est, resid, fund, se))
        noninvasive = resid <= max(o.noninvasive_tol * fund, o.noninvasive_sigmas * se)
        if noninvasive or iters >= o.max_picard or fit is None:
            break
        T = picard_update(T, fit["control"]["mean"], fit["response"]["mean"], s.f, o,
                          s.sample_rate)
    return {"target": A, "estimate": est, "fit": fit, "source": source, "amplitude": amp,
            "parameter": phi, "parameter_se": sphi, "harmonics": T, "noninvasive": noninvasive,
            "gate": gate_ok, "residual": resid, "fundamental": fund, "residual_se": se,
            "picard": iters, "history": rows, "rig_seconds": rig_s,
            "wall_s": time.time() - t_wall}


def _gate(est, o) -> bool:
    r = est.fourier["response"]
    A1 = amplitude(r["mean"])
    spread = math.sqrt(max(r["var"][1], 0.0) + max(r["var"][1 + NH], 0.0))
    return math.isfinite(est.frequency) and spread <= o.variance_rel * max(A1, 1e-9)


def _row(i, stage, A, est, resid, fund, se) -> dict:
    phi, _ = forcing_of(est.fourier["excitation"]["mean"])
    return {"iteration": i, "stage": stage, "target_amplitude": A,
            "amplitude": amplitude(est.fourier["response"]["mean"]), "parameter": phi,
            "control_residual": resid, "control_fundamental": fund, "residual_se": se,
            "invasiveness": resid / fund if fund > 0 else float("inf"),
            "frequency": est.frequency, "rig_time": est.rig_time, "waited_s": est.waited_s}
