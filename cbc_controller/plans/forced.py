"""CBC for the forced (shaker-driven) oscillator: S-curves at fixed frequencies.

Barton's method for a base-excited structure. At each forcing frequency f of
``config["frequencies"]`` the board's target runs on the forcing phase
(``phase_mode`` 0), x*(t) = T0 + A cos(wt) + sum_{k=2..7} (Tak cos kwt + Tbk sin kwt),
and the host's own forcing is off (``forcing_amplitude`` 0): the PD controller
u = kp (x* - x) + kd (x*' - x') is the only excitation. Its fundamental *is* the
forcing; the orbit it sustains is an open-loop orbit of the structure as soon as
the rest of the control (DC and harmonics 2..7) vanishes. So, per point:

1. **Step** the target's fundamental, target_a1 = A, target_b1 = 0, A rising from
   ``amplitude_start``. Because the controller fixes the response amplitude rather
   than the forcing, one sweep in A passes both folds of the S-curve and holds the
   unstable middle branch on the way (proportional feedback stabilises it).
2. **Picard iteration** on the DC and harmonics 2..7: target <- measured response
   coefficients, until the control is *non-invasive*:

       ||(c0, c2..c7, s2..s7)|| <= max(noninvasive_tol * |c1 + i s1|,
                                       noninvasive_sigmas * (its standard error))

   (c, s: the control channel's mean cosine/sine coefficients over navg periods;
   the standard error is sqrt(sum var / navg) of the same 13 coefficients, i.e. the
   residual is either below ``noninvasive_tol`` of the fundamental or
   indistinguishable from the sensor-noise floor). The first target of a point is
   the secant extrapolation of the previous two points' converged harmonics.
3. **Variance gate**: steady when the per-period spread of the response's
   fundamental, sqrt(var a1 + var b1), is below ``variance_rel`` of its amplitude;
   otherwise wait navg more periods (at most ``max_gate_polls`` times).
4. **Record**: ``record_s`` rig seconds of full-rate samples; the estimate that
   ends with them is the point's estimate (non-invasiveness is checked on it
   again: status ``ok`` or ``not_converged``).

Each point: ``amplitude`` = first-harmonic amplitude of the response
hypot(a1, b1) (m); ``parameter`` = the forcing amplitude that sustains it = the
first-harmonic amplitude of the *total* excitation channel (forcing + control;
here the control alone) (m/s^2); ``frequency`` = the forcing frequency (Hz).

**Step control** (adaptive). The next target is A + h. h grows x1.5 when the
S-curve, in coordinates normalised by the largest A and Phi seen so far, turns by
less than ``turn_max_deg``/3 between the last two secants, and halves when it
turns by more than ``turn_max_deg``; it stays within [step_min, step_max]. When the
parabola through the last three points has its vertex (a fold) within the next
step, the step is cut to half the distance to it (not below step_min), so a fold
is approached in shrinking steps and crossed by a step of about step_min: the
points next to a fold are close to it, which keeps the slope estimate below honest.

**End of a sweep**. Folds are confirmed with hysteresis: the jump-up fold once
Phi has fallen ``fold_margin`` (relative, plus 3 standard errors) below its
running maximum, the jump-down fold once it has risen as much above the running
minimum after that. The sweep ends ``beyond_fold`` x the jump-down fold's amplitude
past it (1.2 x by default), or at ``amplitude_stop`` when that is set (> 0), and in
any case at ``amplitude_max`` or once Phi exceeds ``phi_max`` (the shaker's range).
Each confirmed fold is emitted as a ``note`` (its location from the parabola vertex).

**Stability** from branch geometry, point by point: on an S-curve traced with
amplitude increasing monotonically the middle branch, between the folds, is the
one where the sustaining forcing falls as the amplitude rises (dPhi/dA < 0), and
it is unstable (a saddle of the period map: its multiplier crosses +1 at the
folds); dPhi/dA > 0 is stable. dPhi/dA at a point is the derivative, at that point,
of the parabola through it and the two previous points of its sweep (the first
points use the origin, which lies on every S-curve: zero forcing, rest). Its
standard error (from the excitation's variance) is kept in ``extra`` with
``label_confident`` = |slope| > 3 sigma; near a fold the sign is decided by
curvature, not noise, because the step control puts the points close to it.

**Faults.** A ``RigFault`` thrown into a point (the engine has disarmed the rig
and reset the latch) is noted, the rig is re-armed and the point retried at half
the step from the previous point; after ``max_fault_retries`` failures, or when
the halved step would fall under step_min, the target is skipped with a note and
the sweep goes on one step further. ``max_fault_skips`` consecutive skips end the
frequency. ``RigRestarted`` (link lost; the engine re-applied the settings) voids
the point in progress: re-arm and redo it.

**Resume.** Keys are ``f=<Hz, 3 decimals>/A=<target amplitude, m, 6 decimals>``.
Keys in ``ctx.done`` are not emitted again. The sweep's state (the (A, Phi) history
its step control, fold bookkeeping and stability slopes need) is rebuilt from
``ctx.previous`` when its entries are mappings with ``key``, ``amplitude`` and
``parameter``; a done key without such a summary is re-measured, not emitted.
The sweep then goes on from the largest done amplitude.

Gains (defaults). The rig's linear stiffness per unit mass is (2 pi 18 Hz)^2 ~
1.28e4 1/s^2 and the steepest middle branch in 20..26 Hz falls at ~2.5e4 m/s^2 per m;
kp = 3e4 1/s^2 dominates both, and kd = 100 1/s (closed-loop damping ~ 0.25 at
~33 Hz) damps the closed loop within a forcing period or two. At the 3rd harmonic
the closed loop passes ~30 % of a target change, so Picard contracts its error by
~0.3 per iteration (higher gains would slow it). See ``DEFAULTS``.
"""

from __future__ import annotations

import math
import re
import time
from collections.abc import Mapping

import numpy as np

from ..engine import amplitude
from ..messages import Arm, Configure, Disarm, Emit, RigFault, RigRestarted, Settle

NH = 7                 # harmonics in the board's Fourier series
STABILITY_METHOD = ("branch geometry: sign of dPhi/dA at the point (parabola through it and "
                    "the two previous points of the amplitude sweep; the origin anchors the "
                    "first); dPhi/dA < 0 = middle branch between the folds = unstable")

DEFAULTS = {
    # controller (board settings)
    "kp": 3.0e4,                 # proportional gain, (m/s^2)/m
    "kd": 100.0,                 # derivative gain, (m/s^2)/(m/s)
    "filter_hz": 0.0,            # error low-pass on the board, 0 = off
    "navg": 8,                   # periods in the board's running mean/variance
    "transient_periods": 3,      # periods dropped after a new target
    "clamp": 100.0,              # output clamp, m/s^2 (the shaker's limit)
    "trip": 0.016,               # amplitude trip on |x|, m
    "forcing_amplitude": 0.0,    # host forcing (0: the controller provides all of it)
    # amplitude sweep (m)
    "amplitude_start": 3.0e-4,
    "amplitude_step": 3.0e-4,    # first step
    "step_min": 4.0e-5,
    "step_max": 6.0e-4,
    "turn_max_deg": 20.0,
    "amplitude_stop": 0.0,       # > 0: end every sweep here instead of past the folds
    "amplitude_max": 0.012,
    "beyond_fold": 0.2,          # go on to (1 + beyond_fold) x the jump-down fold amplitude
    "phi_max": 80.0,             # end a sweep once the sustaining forcing exceeds this, m/s^2
    "fold_margin": 0.02,
    # convergence
    "max_picard": 8,
    "noninvasive_tol": 0.005,
    "noninvasive_sigmas": 3.0,
    "variance_rel": 0.004,
    "max_gate_polls": 4,
    "record_s": 0.25,
    # faults
    "max_fault_retries": 2,
    "max_fault_skips": 3,
    "max_restarts": 3,
}


def point_key(f: float, A: float) -> str:
    return f"f={f:.3f}/A={A:.6f}"


_KEY = re.compile(r"^f=([0-9.]+)/A=([0-9.]+)$")


def _zero_targets() -> dict:
    t = {"target_a0": 0.0}
    for k in range(1, NH + 1):
        t[f"target_a{k}"] = 0.0
        t[f"target_b{k}"] = 0.0
    return t


def _harm_index():
    """Indices of DC and harmonics 2..7 (a and b) in the 15-coefficient vector."""
    return [0] + list(range(2, NH + 1)) + list(range(NH + 2, 2 * NH + 1))


HIGHER = _harm_index()


def invasiveness(est, navg: int) -> tuple[float, float, float]:
    """(residual, fundamental, standard error of the residual) of the control:
    residual = norm of its DC and harmonics 2..7, fundamental = hypot(c1, s1)."""
    c = np.asarray(est.fourier["control"]["mean"], dtype=float)
    v = np.asarray(est.fourier["control"]["var"], dtype=float)
    resid = float(np.sqrt(np.sum(c[HIGHER] ** 2)))
    fund = float(math.hypot(c[1], c[1 + NH]))
    se = float(np.sqrt(max(np.sum(np.maximum(v[HIGHER], 0.0)), 0.0) / max(navg, 1)))
    return resid, fund, se


def forcing_of(est, navg: int) -> tuple[float, float]:
    """(Phi, its standard error): first-harmonic amplitude of the total excitation."""
    e = np.asarray(est.fourier["excitation"]["mean"], dtype=float)
    v = np.asarray(est.fourier["excitation"]["var"], dtype=float)
    phi = float(math.hypot(e[1], e[1 + NH]))
    if phi <= 0:
        return phi, 0.0
    var = (e[1] ** 2 * max(v[1], 0.0) + e[1 + NH] ** 2 * max(v[1 + NH], 0.0)) / phi ** 2
    return phi, float(math.sqrt(var / max(navg, 1)))


def _parabola(pts):
    """Coefficients (c2, c1, c0) of the parabola through three (A, Phi) points."""
    (x0, y0), (x1, y1), (x2, y2) = pts
    return np.polyfit([x0, x1, x2], [y0, y1, y2], 2)


def slope_at_last(pts, sig) -> tuple[float, float]:
    """dPhi/dA at the last of (up to) three points from the parabola through them
    (the secant for two), and its standard error from the points' errors `sig`."""
    if len(pts) == 2:
        (x0, y0), (x1, y1) = pts
        w = np.array([-1.0, 1.0]) / (x1 - x0)
    else:
        (x0, _), (x1, _), (x2, _) = pts
        w = np.array([(x2 - x1) / ((x0 - x1) * (x0 - x2)),
                      (x2 - x0) / ((x1 - x0) * (x1 - x2)),
                      (2 * x2 - x0 - x1) / ((x2 - x0) * (x2 - x1))])
    y = np.array([p[1] for p in pts])
    return float(w @ y), float(np.sqrt(np.sum((w * np.asarray(sig)) ** 2)))


class _Sweep:
    """The S-curve at one frequency: history, step control, fold bookkeeping."""

    def __init__(self, f: float, o: dict):
        self.f = float(f)
        self.o = o
        self.pts: list[tuple[float, float]] = [(0.0, 0.0)]   # (A, Phi), origin first
        self.sig: list[float] = [0.0]
        self.targets_done: list[float] = []                  # target amplitudes measured
        self.harm: list[tuple[float, np.ndarray]] = []       # (A target, converged 15-vector)
        self.h = float(o["amplitude_step"])
        self.folds: list[dict] = []
        self.phase = 0                                       # folds confirmed so far
        self.ext_i = 0                                       # index of the running extreme

    # ---------------------------------------------------------------- targets
    def predict_harmonics(self, A: float) -> np.ndarray:
        if not self.harm:
            return np.zeros(2 * NH + 1)
        if len(self.harm) == 1 or self.harm[-1][0] == self.harm[-2][0]:
            return self.harm[-1][1].copy()
        (A0, T0), (A1, T1) = self.harm[-2], self.harm[-1]
        w = (A - A1) / (A1 - A0)
        w = max(min(w, 1.5), -1.0)              # do not extrapolate wildly
        return T1 + w * (T1 - T0)

    def settings(self, A: float, T: np.ndarray) -> dict:
        t = {"target_a0": float(T[0]), "target_a1": float(A), "target_b1": 0.0}
        for k in range(2, NH + 1):
            t[f"target_a{k}"] = float(T[k])
            t[f"target_b{k}"] = float(T[k + NH])
        return t

    # ---------------------------------------------------------------- bookkeeping
    def add(self, A_target: float, A: float, phi: float, sphi: float, T: np.ndarray):
        """Record a measured point; returns (slope, slope_se) at it."""
        self.pts.append((A, phi))
        self.sig.append(sphi)
        self.targets_done.append(A_target)
        self.harm.append((A_target, T.copy()))
        return slope_at_last(self.pts[-3:], self.sig[-3:])

    def update_folds(self):
        """Confirm folds with hysteresis; returns a new fold's record or None."""
        if self.phase >= 2 or len(self.pts) < 3:
            return None
        i = len(self.pts) - 1
        phi_i = self.pts[i][1]
        ext = self.pts[self.ext_i][1]
        margin = self.o["fold_margin"] * max(ext, 1e-12) + 3.0 * max(self.sig[i], self.sig[self.ext_i])
        if self.phase == 0:
            if phi_i >= ext:
                self.ext_i = i
                return None
            if phi_i < ext - margin:
                return self._confirm(kind="jump-up")
        else:
            if phi_i <= ext:
                self.ext_i = i
                return None
            if phi_i > ext + margin:
                return self._confirm(kind="jump-down")
        return None

    def _confirm(self, kind: str) -> dict:
        j = self.ext_i
        A_f, phi_f = self.pts[j]
        if 1 <= j < len(self.pts) - 1:
            c2, c1, c0 = _parabola(self.pts[j - 1:j + 2])
            if c2 != 0:
                Av = -c1 / (2 * c2)
                if self.pts[j - 1][0] <= Av <= self.pts[j + 1][0]:
                    A_f, phi_f = float(Av), float(np.polyval([c2, c1, c0], Av))
        fold = {"kind": kind, "amplitude": A_f, "parameter": phi_f, "frequency": self.f}
        self.folds.append(fold)
        self.phase += 1
        self.ext_i = len(self.pts) - 1
        return fold

    def finished(self, A_next: float) -> str:
        """Why the sweep ends before measuring at A_next ('' to go on)."""
        o = self.o
        A_last = self.targets_done[-1] if self.targets_done else 0.0
        if len(self.pts) > 1 and self.pts[-1][1] > o["phi_max"]:
            return f"forcing {self.pts[-1][1]:.1f} m/s^2 above phi_max"
        if o["amplitude_stop"] > 0:
            if A_next > o["amplitude_stop"] + 1e-9:
                return "amplitude_stop reached"
        elif self.phase >= 2 and A_last >= (1 + o["beyond_fold"]) * self.folds[1]["amplitude"]:
            return "past both folds"
        if A_next > o["amplitude_max"] + 1e-9:
            return "amplitude_max reached"
        return ""

    def next_step(self) -> float:
        """Adapt h after a point (turning angle, fold approach); returns it."""
        o = self.o
        h = self.h
        if len(self.pts) >= 3:
            Aref = max(p[0] for p in self.pts)
            Pref = max(p[1] for p in self.pts) or 1.0
            (a0, p0), (a1, p1), (a2, p2) = [(a / Aref, p / Pref) for a, p in self.pts[-3:]]
            v1 = np.array([a1 - a0, p1 - p0])
            v2 = np.array([a2 - a1, p2 - p1])
            n = np.linalg.norm(v1) * np.linalg.norm(v2)
            if n > 0:
                ang = math.degrees(math.acos(max(-1.0, min(1.0, float(v1 @ v2) / n))))
                if ang > o["turn_max_deg"]:
                    h *= 0.5
                elif ang < o["turn_max_deg"] / 3:
                    h *= 1.5
        h = min(max(h, o["step_min"]), o["step_max"])
        if len(self.pts) >= 4 and self.phase < 2:
            c2, c1, _ = _parabola(self.pts[-3:])
            A_i = self.pts[-1][0]
            if c2 != 0:
                Av = -c1 / (2 * c2)
                if A_i < Av < A_i + h:            # a fold ahead within the step: approach it
                    h = max(o["step_min"], 0.5 * (Av - A_i))
        self.h = h
        return h


def oscillator_plan(config: dict):
    """Build the plan for an oscillator campaign from its (validated) config."""
    o = {**DEFAULTS, **config.get("cbc", {})}
    o["navg"] = int(o["navg"])
    freqs = [float(f) for f in config["frequencies"]]

    def plan(ctx):
        state = {"index": len(ctx.previous)}
        summaries = _summaries(ctx)
        yield Configure({"kp": o["kp"], "kd": o["kd"], "navg": o["navg"], "phase_mode": 0,
                         "clamp": o["clamp"], "trip": o["trip"], "filter_hz": o["filter_hz"],
                         "forcing_amplitude": o["forcing_amplitude"], "frequency": freqs[0],
                         **_zero_targets()})
        for f in freqs:
            s = _Sweep(f, o)
            yield from _run_sweep(s, o, ctx, summaries, state)
        yield Disarm()

    return plan


def _summaries(ctx) -> dict:
    """key -> (amplitude, parameter) from ctx.previous, where it carries them."""
    out = {}
    for p in ctx.previous or []:
        if isinstance(p, Mapping) and {"key", "amplitude", "parameter"} <= set(p):
            try:
                out[str(p["key"])] = (float(p["amplitude"]), float(p["parameter"]))
            except (TypeError, ValueError):
                continue
    return out


def _done_targets(ctx, f: float) -> list[float]:
    out = []
    for k in ctx.done:
        m = _KEY.match(str(k))
        if m and abs(float(m.group(1)) - f) < 5e-4:
            out.append(float(m.group(2)))
    return sorted(out)


def _run_sweep(s: _Sweep, o: dict, ctx, summaries: dict, state: dict):
    """Generator: the whole sweep at one frequency."""
    yield Configure({"frequency": s.f, "forcing_amplitude": o["forcing_amplitude"],
                     "phase_mode": 0, **_zero_targets()})
    yield Arm()
    replay = _done_targets(ctx, s.f)      # already in the file: rebuild the state, emit nothing
    A = replay.pop(0) if replay else round(o["amplitude_start"], 6)
    prev_A = None                         # target of the last measured point
    skips = 0
    why = ""
    while True:
        key = point_key(s.f, A)
        if key in summaries and key in ctx.done:
            amp, phi = summaries[key]
            s.add(A, amp, phi, 0.0, s.predict_harmonics(A))
            s.update_folds()
            prev_A = A
        else:
            res = yield from _attempt(s, o, A, prev_A)
            if res is None:                   # lost to faults: skipped
                skips += 1
                if skips >= o["max_fault_skips"]:
                    why = f"{skips} targets in a row lost to rig faults"
                    break
                if not replay:
                    A = round(A + s.h, 6)
                    why = s.finished(A)
                    if why:
                        break
                    continue
            else:
                skips = 0
                A = res["target"]             # a fault may have moved it
                key = point_key(s.f, A)
                slope = s.add(A, res["amplitude"], res["parameter"], res["parameter_se"],
                              res["harmonics"])
                fold = s.update_folds()
                if key not in ctx.done:
                    yield Emit("point", _point_doc(state["index"], key, s, res, o, slope))
                    state["index"] += 1
                if fold is not None:
                    yield Emit("note", {"text": f"f = {s.f:g} Hz: {fold['kind']} fold near "
                                                f"A = {fold['amplitude'] * 1e3:.3f} mm, Phi = "
                                                f"{fold['parameter']:.3f} m/s^2", "fold": fold})
                prev_A = A
        if replay:
            A = replay.pop(0)
            continue
        h = s.next_step()
        A = round(prev_A + h, 6) if prev_A is not None else round(A + h, 6)
        why = s.finished(A)
        if why:
            break
    yield Emit("note", {"text": f"f = {s.f:g} Hz: sweep ended ({why}); "
                                f"{len(s.pts) - 1} points, {len(s.folds)} folds",
                        "folds": s.folds})


def _attempt(s: _Sweep, o: dict, A: float, prev_A):
    """Generator: measure the point at target A, handling faults and restarts.
    Returns the measurement dict or None (skipped)."""
    faults = 0
    restarts = 0
    while True:
        try:
            res = yield from _measure(s, o, A)
            return res
        except RigRestarted:
            restarts += 1
            yield Emit("note", {"text": f"f = {s.f:g} Hz, A = {A * 1e3:.3f} mm: link lost; "
                                        "point repeated"})
            if restarts > o["max_restarts"]:
                return None
            yield from _rearm()
        except RigFault as exc:
            faults += 1
            base = prev_A if prev_A is not None else 0.0
            new_A = round(base + 0.5 * (A - base), 6)
            if faults > o["max_fault_retries"] or (new_A - base) < o["step_min"] or prev_A is None:
                yield Emit("note", {"text": f"f = {s.f:g} Hz: {exc} at target A = "
                                            f"{A * 1e3:.3f} mm; target skipped"})
                yield from _rearm()
                return None
            yield Emit("note", {"text": f"f = {s.f:g} Hz: {exc} at target A = {A * 1e3:.3f} mm; "
                                        f"retrying at {new_A * 1e3:.3f} mm"})
            A = new_A
            s.h = max(o["step_min"], new_A - base)
            yield from _rearm()


def _rearm():
    """Arm again after a fault or a reconnect (a fault while arming is retried)."""
    for _ in range(3):
        try:
            yield Arm()
            return
        except (RigFault, RigRestarted):
            continue
    yield Arm()


def _measure(s: _Sweep, o: dict, A: float):
    """Generator: Picard iteration, variance gate and record at target amplitude A."""
    navg = o["navg"]
    t_wall = time.time()
    T = s.predict_harmonics(A)
    rows = []
    est = None
    ok_inv = False
    for it in range(int(o["max_picard"])):
        yield Configure(s.settings(A, T))
        est = yield Settle(periods=int(o["transient_periods"]) + navg)
        resid, fund, se = invasiveness(est, navg)
        ok_inv = resid <= max(o["noninvasive_tol"] * fund, o["noninvasive_sigmas"] * se)
        rows.append(_row(len(rows), "picard", A, est, resid, fund, se, navg))
        if ok_inv:
            break
        r = np.asarray(est.fourier["response"]["mean"], dtype=float)
        T = T.copy()
        T[HIGHER] = r[HIGHER]
    gate_ok = False
    for _ in range(int(o["max_gate_polls"]) + 1):
        gate_ok = _gate(est, o)
        if gate_ok:
            break
        yield Configure(s.settings(A, T))
        est = yield Settle(periods=navg)
        resid, fund, se = invasiveness(est, navg)
        rows.append(_row(len(rows), "gate", A, est, resid, fund, se, navg))
    # the record: the estimate read after it covers its last navg periods
    if o["record_s"] > 0:
        est = yield Settle(periods=0, record_s=float(o["record_s"]))
    resid, fund, se = invasiveness(est, navg)
    ok_inv = resid <= max(o["noninvasive_tol"] * fund, o["noninvasive_sigmas"] * se)
    gate_ok = _gate(est, o)
    rows.append(_row(len(rows), "record", A, est, resid, fund, se, navg))
    phi, sphi = forcing_of(est, navg)
    return {"target": A, "estimate": est, "amplitude": amplitude(est.fourier["response"]["mean"]),
            "parameter": phi, "parameter_se": sphi, "harmonics": T, "noninvasive": ok_inv,
            "gate": gate_ok, "residual": resid, "fundamental": fund, "residual_se": se,
            "picard": sum(1 for r in rows if r["stage"] == "picard"), "history": rows,
            "wall_s": time.time() - t_wall}


def _gate(est, o) -> bool:
    r = est.fourier["response"]
    A1 = amplitude(r["mean"])
    spread = math.sqrt(max(r["var"][1], 0.0) + max(r["var"][1 + NH], 0.0))
    return math.isfinite(est.frequency) and spread <= o["variance_rel"] * max(A1, 1e-9)


def _row(i, stage, A, est, resid, fund, se, navg) -> dict:
    phi, _ = forcing_of(est, navg)
    return {"iteration": i, "stage": stage, "target_amplitude": A,
            "amplitude": amplitude(est.fourier["response"]["mean"]), "parameter": phi,
            "control_residual": resid, "control_fundamental": fund, "residual_se": se,
            "invasiveness": resid / fund if fund > 0 else float("inf"),
            "frequency": est.frequency, "rig_time": est.rig_time, "waited_s": est.waited_s}


def _point_doc(index, key, s: _Sweep, res: dict, o: dict, slope) -> dict:
    est = res["estimate"]
    resp = np.asarray(est.fourier["response"]["mean"])
    exc = np.asarray(est.fourier["excitation"]["mean"])
    ts = est.samples or {}
    dphi, dphi_se = slope
    stable = bool(dphi > 0)
    extra = {"target_amplitude": res["target"], "dc": float(resp[0]),
             "picard_iterations": res["picard"], "evaluations": len(res["history"]),
             "control_residual": res["residual"], "control_fundamental": res["fundamental"],
             "invasiveness": res["residual"] / res["fundamental"] if res["fundamental"] > 0 else float("inf"),
             "control_residual_se": res["residual_se"], "noninvasive": bool(res["noninvasive"]),
             "variance_gate": bool(res["gate"]), "parameter_se": res["parameter_se"],
             "dphi_da": dphi, "dphi_da_se": dphi_se,
             "label_confident": bool(abs(dphi) > 3 * dphi_se),
             "forcing_phase": float(math.atan2(exc[1 + NH], exc[1])),
             "response_phase": float(math.atan2(resp[1 + NH], resp[1])),
             "folds_passed": s.phase, "step": s.h,
             "rig_seconds": float(sum(r["waited_s"] for r in res["history"]))}
    if ts.get("x") is not None and len(ts["x"]):
        extra["control_rms"] = float(np.sqrt(np.mean(np.asarray(ts["control"]) ** 2)))
        extra["response_rms"] = float(np.sqrt(np.mean((np.asarray(ts["x"]) - resp[0]) ** 2)))
        extra["gap_records"] = int(ts.get("gap_records", 0))
    timeseries = {k: np.asarray(v) for k, v in ts.items() if k != "gap_records"}
    settings = {"kp": o["kp"], "kd": o["kd"], "filter_hz": o["filter_hz"], "navg": o["navg"],
                "frequency": s.f, "forcing_amplitude": o["forcing_amplitude"], "phase_mode": 0,
                **s.settings(res["target"], res["harmonics"])}
    return {
        "index": index, "key": key, "rig": "oscillator", "parameter": float(res["parameter"]),
        "parameter_name": "forcing_amplitude", "frequency": float(s.f),
        "amplitude": float(res["amplitude"]), "stable": stable,
        "stability_method": STABILITY_METHOD,
        "status": "ok" if (res["noninvasive"] and res["gate"]) else "not_converged",
        "settings": settings,
        "fourier": {ch: {"mean": np.asarray(v["mean"]), "var": np.asarray(v["var"])}
                    for ch, v in est.fourier.items()},
        "history": res["history"], "rig_time": est.rig_time, "wall_time": res["wall_s"],
        "timeseries": timeseries, "extra": extra,
    }
