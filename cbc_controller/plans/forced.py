"""CBC for the forced (shaker-driven) oscillator: S-curves at fixed frequencies.

Barton's method for a base-excited structure. At each forcing frequency f of
``config["frequencies"]`` the board's target runs on the forcing phase
(``phase_mode`` 0), x*(t) = T0 + A cos(wt) + sum_{k=2..7} (Tak cos kwt + Tbk sin kwt),
and the host's own forcing is off (``forcing_amplitude`` 0, configurable as a
feed-forward): the PD controller u = kp (x* - x) + kd (x*' - x') is then the only
excitation. Its fundamental *is* the forcing; the orbit it sustains is an
open-loop orbit of the structure as soon as the rest of the control (DC and
harmonics 2..7) vanishes. Per point:

1. **Step** the target's fundamental, target_a1 = A, target_b1 = 0, A rising from
   ``amplitude_start``. The controller fixes the response amplitude rather than
   the forcing, so one sweep in A passes both folds of the S-curve and holds the
   unstable middle branch on the way.
2. **Picard iteration** on the DC and harmonics 2..7 (target <- the response's),
   until the control is *non-invasive*:

       r = ||(c0, c2..c7, s2..s7)|| <= max(noninvasive_tol * |c1 + i s1|,
                                           noninvasive_sigmas * se(r))

   (c, s: the control channel's mean cosine/sine coefficients over navg periods;
   se(r) = sqrt(sum var / navg) of the same 13 coefficients: the residual is either
   below ``noninvasive_tol`` of the fundamental or indistinguishable from the
   sensor-noise floor: pure noise has |r| ~ se(r), and |r| > 2 se(r) in well under
   1 % of cases). The response harmonics are read *through the controller*,
   x_k = T_k - u_k / C(k w) (C the board's PD law, known exactly), see
   `picard_update` for why. The first target of a point is the secant extrapolation
   of the previous two points' converged harmonics.
3. **Variance gate**: steady when the per-period spread of the response's
   fundamental, sqrt(var a1 + var b1), is below ``variance_rel`` of its amplitude;
   otherwise wait navg more periods (at most ``max_gate_polls`` times).
4. **Record** ``record_s`` rig seconds of full-rate samples and fit the Fourier
   series (DC + 7 harmonics) of the response, the control and the total excitation
   to them by least squares against the recorded forcing phase. These are the
   point's numbers: ``amplitude`` = hypot(a1, b1) of the response (m),
   ``parameter`` = hypot(a1, b1) of the total excitation, the forcing that
   sustains the orbit (m/s^2), ``frequency`` = the forcing frequency (Hz).
   Non-invasiveness is checked again on the fitted control (se from the fit's
   residual); if it fails, Picard goes on from the fitted coefficients and the
   point is recorded again (``max_picard`` iterations in all; status ``ok`` or
   ``not_converged``). Why not the board's estimate: when a forcing period is not a
   whole number of samples (23 Hz at 10 kHz: 434.8) the board's running correlation
   biases the fundamental by ~0.1-0.2 %; on the upper branch next to the jump-down
   fold Phi changes 20-50x faster than A in relative terms, so that bias alone is a
   2-5 % error in Phi at the measured amplitude. The board's estimates stay in
   ``fourier`` (mean and variance) and the fitted ones are in ``extra``.

**Step control** (adaptive). The next target is A + h. h grows x1.5 when the
S-curve, in coordinates normalised by the largest A and Phi seen so far, turns by
less than ``turn_max_deg``/3 between the last two secants, and halves when it
turns by more than ``turn_max_deg``; it stays within [step_min, step_max]. Two
fold guards: when the parabola through the last three points has its vertex
within the next step, the step is cut to half the distance to it; on a falling
branch the step is limited so that the linear prediction of Phi drops by at most
``descent_frac`` of Phi (Phi is an amplitude, so the branch must turn before
zero: this is what finds the sharp jump-down fold).

**End of a sweep**. Folds are confirmed with hysteresis: the jump-up fold once
Phi has fallen ``fold_margin`` (relative, plus 3 standard errors) below its
running maximum, the jump-down fold once it has risen as much above the running
minimum after that. The sweep ends at (1 + ``beyond_fold``) x the jump-down fold's
amplitude, or at ``amplitude_stop`` when that is set (> 0), and in any case once the
response amplitude or the sustaining forcing, predicted for the next step, would
exceed ``amplitude_max`` or ``phi_max``. Each confirmed fold is emitted as
a ``note`` (located at the vertex of the least-squares parabola through the
points within 2 % of the extreme point's amplitude, at least its two neighbours).

**Stability** from branch geometry, point by point: traced with the amplitude
increasing monotonically, the middle branch between the folds is where the
sustaining forcing falls as the amplitude rises (dPhi/dA < 0); it is unstable
(its Floquet multiplier crosses +1 at each fold); dPhi/dA > 0 is stable. At a point,
dPhi/dA is the derivative of the parabola through it and the two previous points
of its sweep (the origin, on every S-curve, anchors the first two). Where that
disagrees with the previous point's label (a fold between them), is within 3
standard errors of zero, or puts the parabola's vertex within half a step of the
point (a fold right there, where a parabola over the last steps is least
trustworthy: the jump-down fold is nearly a corner), a *probe* is measured at
target A - eps (eps balancing the parabola's curvature against the noise of Phi)
and the label is the sign of the secant between the probe and the point, i.e. of
dPhi/dA within eps of the point. The probe is not a point of the curve (it is in
``extra['probe']``). A label can then only be wrong within ~eps/2 of a fold, or
where the true forcing is within its noise (~0.003 m/s^2 here) of the fold's; the
slope and its standard error are in ``extra`` (``label_confident`` = |dPhi/dA| > 3 se).

**Fold refinement.** When the labels of two successive sweep points differ, a fold
lies between them: up to ``fold_refine`` points bisect that interval (in target
amplitude) until the bracket is under ``fold_gap`` of the amplitude, each labelled
by its own probe (``extra['refinement']`` = True; emitted as soon as measured, so
the file is not in amplitude order there). They locate the fold notes and give the
fit the data next to the folds; the sweep then goes on from where it was.

**Faults.** A ``RigFault`` thrown into a point (the engine has disarmed the rig
and reset the latch) is noted; the rig rings down disarmed, is re-armed on a
target ramped up to ``rearm_fraction`` of the last good point's, and the point is
retried at half the step from the previous point; after ``max_fault_retries`` failures, or when
the halved step would fall under step_min, the target is skipped with a note and
the sweep goes on one step further. ``max_fault_skips`` consecutive skips end the
frequency. ``RigRestarted`` (link lost; the engine re-applied the settings) voids
the point in progress: re-arm and redo it.

**Resume.** Keys are ``f=<Hz, 3 decimals>/A=<target amplitude, m, 6 decimals>``.
Each frequency's sweep is a segment: it starts with the rig at rest and its noise
streams seeded from the campaign's seed and the frequency (`Reseed`, lockstep rigs), so
it measures the same numbers whenever it runs. A sweep is done once a later frequency
has points in the file; the last one begun is measured again from its start and only
the points the file lacks are emitted (keys in ``ctx.done`` never are), so a resumed
lockstep campaign logs exactly the points of one never interrupted.

**Gains** (defaults kp = 1e4 1/s^2, kd = 50 1/s). Two requirements, checked with
a one-harmonic model of this rig (linear stiffness per unit mass (2 pi 18 Hz)^2 ~
1.28e4 1/s^2, hardening) over 20-26 Hz and up to 1.2x the jump-down fold:
(a) the controlled system's response amplitude must rise monotonically with the
target (no fold of the closed loop, so the middle branch is held): kp = 1e4 with
kd = 50 does at 20, 23 and 26 Hz (so do kp = 0 with kd >= 50, or kp = 1.5e4 with
kd = 0; kp = 1e4 with kd = 0 leaves a fold at 26 Hz);
(b) Picard contracts at harmonic k by |C/(C + P^-1)|(k w) (P the plant, C = kp +
i k w kd): above the plant's resonance a large kp puts the *closed-loop*
resonance on 2w and the iteration diverges (kp = 3e4, kd = 100 gives 1.2-1.35 at 2w
on the upper branch; measured: the DC and 2nd harmonic run away near the jump-down
fold). kp = 1e4, kd = 50 gives 0.46 at 2w, 0.2 at 3w, 0.43 at DC, with sensor-noise
control of ~0.1 m/s^2 rms (kd x 2 mm/s).
"""

from __future__ import annotations

import math
import re

import numpy as np

from ..harmonics import NH, amplitude
from ..messages import Arm, Configure, Disarm
from ._steps import PointLog, lost_to_fault, note, point_doc, start_segment
from .forced_numbers import centred_slope, forcing_of, parabola, zero_targets
from .forced_point import attempt, probe
from .options import ForcedOptions
from .scurve import Sweep

STABILITY_METHOD = ("branch geometry: sign of dPhi/dA at the point along the monotonic amplitude "
                    "sweep (parabola through it and the two previous points; near a fold the "
                    "secant to a probe point just below it); dPhi/dA < 0 = middle branch "
                    "between the folds = unstable")
DEFAULTS = ForcedOptions().as_dict()     # the options' defaults, as a table
_KEY = re.compile(r"^f=([0-9.]+)/A=([0-9.]+)$")


def point_key(f: float, A: float) -> str:
    return f"f={f:.3f}/A={A:.6f}"


def oscillator_plan(config: dict):
    """Build the plan for an oscillator campaign from its (validated) config."""
    o = ForcedOptions.from_table(config.get("cbc"))
    freqs = [float(f) for f in config["frequencies"]]

    def plan(ctx):
        sample_rate = float((ctx.identity or {}).get("sample_rate", 10000.0))
        points = PointLog(ctx)
        settings = {"kp": o.kp, "kd": o.kd, "navg": o.navg, "phase_mode": 0,
                    "clamp": o.clamp, "trip": o.trip, "filter_hz": o.filter_hz,
                    "forcing_amplitude": o.forcing_amplitude, "frequency": freqs[0],
                    **zero_targets()}
        if (yield from lost_to_fault(Configure(settings))):   # lost before it was written
            yield Configure(settings)                           # once more
        for i, f in enumerate(freqs):
            # a sweep in the file is done once a later one has begun; the last begun is
            # measured again from its start, emitting what the file lacks (see Resume)
            if _begun(points.done, freqs[i + 1:]):
                continue
            yield from _run_sweep(Sweep(f, o, sample_rate), o, ctx, points)
        yield from lost_to_fault(Disarm())                      # disarmed either way

    return plan


def _begun(done, freqs) -> bool:
    """Whether the file has points of any of these frequencies (keys hold 3 decimals)."""
    logged = [float(m.group(1)) for m in map(_KEY.match, map(str, done)) if m]
    return any(abs(f - g) < 5e-4 for f in logged for g in freqs)


def _run_sweep(s: Sweep, o: ForcedOptions, ctx, points: PointLog):
    """Generator: the whole sweep at one frequency, a segment of its own (from rest, its
    own noise streams)."""
    start = {"frequency": s.f, "forcing_amplitude": o.forcing_amplitude, "phase_mode": 0,
             **zero_targets()}
    if (yield from lost_to_fault(start_segment(ctx, f"f={s.f:.3f}"), Configure(start), Arm())):
        s.armed = False                   # the first point re-arms (and re-configures)
        yield Configure(start)
    A = round(o.amplitude_start, 6)
    prev_A = None                         # target of the last measured point
    last = None                           # its measurement
    skips = 0
    why = ""
    while True:
        res = yield from attempt(s, o, A, prev_A)
        if res is None:                   # lost to faults: skipped
            skips += 1
            if skips >= o.max_fault_skips:
                why = f"{skips} targets in a row lost to rig faults"
                break
            A = round(A + s.h, 6)
            why = s.finished(A)
            if why:
                break
            continue
        skips = 0
        A = res["target"]                 # a fault may have moved it
        key = point_key(s.f, A)
        slope, se, c2 = s.add(A, res["amplitude"], res["parameter"],
                              res["parameter_se"], res["harmonics"])
        label = {"slope": slope, "slope_se": se, "method": "parabola", "probe": None}
        prev_label = s.labels[-1] if s.labels else True   # the origin: stable rest
        spacing = s.pts[-1][0] - s.pts[-2][0]
        near_vertex = c2 != 0 and abs(slope / (2 * c2)) < 0.5 * spacing
        if (slope > 0) != prev_label or abs(slope) <= 3 * se or near_vertex:
            below = s.targets_done[-2] if len(s.targets_done) >= 2 else 0.0
            slope_below = yield from probe(s, o, res, c2, below)
            if slope_below is not None:
                label.update(slope_below)
        s.labels.append(label["slope"] > 0)
        yield from points.emit(key, lambda i: _point_doc(i, key, s, res, o, label))
        if last is not None and s.labels[-1] != s.labels[-2]:
            # a fold between the last two points: close in on it
            yield from _refine_fold(s, o, points, last, res)
        fold = s.update_folds()
        if fold is not None:
            yield note(f"f = {s.f:g} Hz: {fold['kind']} fold near A = "
                       f"{fold['amplitude'] * 1e3:.3f} mm, Phi = "
                       f"{fold['parameter']:.3f} m/s^2", fold=fold)
        last = res
        prev_A = A
        A = round(A + s.next_step(), 6)
        why = s.finished(A)
        if why:
            break
    yield note(f"f = {s.f:g} Hz: sweep ended ({why}); {len(s.pts) - 1} points, "
               f"{len(s.folds)} folds", folds=s.folds)


def _refine_fold(s: Sweep, o: ForcedOptions, points: PointLog, lo: dict, hi: dict):
    """Generator: bisect (in target amplitude) between two points whose labels differ
    until they are less than ``fold_gap`` of the amplitude apart (at most
    ``fold_refine`` points). Each new point is labelled by its own probe (the
    secant just below it), emitted, and kept for locating the fold."""
    lab_lo = s.labels[-2]
    for _ in range(o.fold_refine):
        if hi["amplitude"] - lo["amplitude"] <= o.fold_gap * hi["amplitude"]:
            return
        T = round(0.5 * (lo["target"] + hi["target"]), 6)
        if not lo["target"] < T < hi["target"]:
            return
        res = yield from attempt(s, o, T, lo["target"],
                                 start=0.5 * (lo["harmonics"] + hi["harmonics"]))
        if res is None:
            return
        T = res["target"]
        key = point_key(s.f, T)
        trio = [(lo["amplitude"], lo["parameter"]), (res["amplitude"], res["parameter"]),
                (hi["amplitude"], hi["parameter"])]
        c2 = float(parabola(trio)[0])
        slope, se = centred_slope(trio, [lo["parameter_se"], res["parameter_se"],
                                         hi["parameter_se"]])
        label = {"slope": slope, "slope_se": se, "method": "centred parabola", "probe": None,
                 "refinement": True}
        slope_below = yield from probe(s, o, res, c2, lo["target"])
        if slope_below is not None:
            label.update(slope_below)
        s.extra.append((res["amplitude"], res["parameter"]))
        yield from points.emit(key, lambda i: _point_doc(i, key, s, res, o, label))
        if (label["slope"] > 0) == lab_lo:
            lo = res
        else:
            hi = res



def _point_doc(index, key, s: Sweep, res: dict, o: ForcedOptions, label: dict) -> dict:
    est = res["estimate"]
    resp = np.asarray(est.fourier["response"]["mean"])
    fit = res["fit"]
    coef = fit["response"]["mean"] if fit else resp
    exc = fit["excitation"]["mean"] if fit else np.asarray(est.fourier["excitation"]["mean"])
    extra = {
        "target_amplitude": res["target"], "dc": float(coef[0]),
        "picard_iterations": res["picard"], "evaluations": len(res["history"]),
        "control_residual": res["residual"], "control_fundamental": res["fundamental"],
        "invasiveness": (res["residual"] / res["fundamental"] if res["fundamental"] > 0
                         else float("inf")),
        "control_residual_se": res["residual_se"], "noninvasive": bool(res["noninvasive"]),
        "variance_gate": bool(res["gate"]), "parameter_se": res["parameter_se"],
        "values_from": res["source"],
        "board_amplitude": amplitude(resp),
        "board_parameter": forcing_of(est.fourier["excitation"]["mean"])[0],
        "dphi_da": label["slope"], "dphi_da_se": label["slope_se"],
        "stability_from": label["method"],
        "label_confident": bool(abs(label["slope"]) > 3 * label["slope_se"]),
        "forcing_phase": float(math.atan2(exc[1 + NH], exc[1])),
        "response_phase": float(math.atan2(coef[1 + NH], coef[1])),
        "folds_passed": s.phase, "next_step": s.h, "rig_seconds": res["rig_seconds"],
        "wall_seconds": res["wall_s"],
    }
    extra["refinement"] = bool(label.get("refinement", False))
    if label["probe"] is not None:
        extra["probe"] = label["probe"]
    if fit is not None:
        extra["record_fourier"] = {ch: [float(v) for v in fit[ch]["mean"]]
                                   for ch in ("response", "control", "excitation")}
        extra["record_samples"] = fit["samples"]
    settings = {"kp": o.kp, "kd": o.kd, "filter_hz": o.filter_hz, "navg": o.navg,
                "frequency": s.f, "forcing_amplitude": o.forcing_amplitude, "phase_mode": 0,
                **s.settings(res["target"], res["harmonics"])}
    return point_doc(
        index=index, key=key, rig="oscillator", parameter=res["parameter"],
        parameter_name="forcing_amplitude", frequency=s.f, amplitude=res["amplitude"],
        stable=label["slope"] > 0, stability_method=STABILITY_METHOD,
        converged=res["noninvasive"] and res["gate"], settings=settings, estimate=est,
        dc=coef[0], history=res["history"], wall_time=res["wall_s"], extra=extra)
