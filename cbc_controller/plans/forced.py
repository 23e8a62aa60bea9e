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
Keys in ``ctx.done`` are never emitted again. The sweep's state (the (A, Phi)
history its step control, fold bookkeeping and labels need) is rebuilt from
``ctx.previous`` when its entries are mappings with ``key``, ``amplitude`` and
``parameter`` (and ``stable``); a done key without such a summary is re-measured
but not emitted. The sweep then goes on from the largest done target.

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
import time
from collections.abc import Mapping

import numpy as np

from ..engine import amplitude
from ..messages import Arm, Configure, Disarm, Emit, RigFault, RigRestarted, Settle

NH = 7                 # harmonics in the board's Fourier series
STABILITY_METHOD = ("branch geometry: sign of dPhi/dA at the point along the monotonic amplitude "
                    "sweep (parabola through it and the two previous points; near a fold the "
                    "secant to a probe point just below it); dPhi/dA < 0 = middle branch "
                    "between the folds = unstable")

DEFAULTS = {
    # controller (board settings)
    "kp": 1.0e4,                 # proportional gain, (m/s^2)/m
    "kd": 50.0,                  # derivative gain, (m/s^2)/(m/s)
    "filter_hz": 0.0,            # error low-pass on the board, 0 = off
    "navg": 8,                   # periods in the board's running mean/variance
    "transient_periods": 3,      # periods dropped after a new target
    "clamp": 100.0,              # output clamp, m/s^2 (the shaker's limit)
    "trip": 0.016,               # amplitude trip on |x|, m
    "forcing_amplitude": 0.0,    # host forcing, m/s^2 (0: the controller provides all of it)
    # amplitude sweep (m)
    "amplitude_start": 3.0e-4,
    "amplitude_step": 3.0e-4,    # first step
    "step_min": 4.0e-5,
    "step_max": 6.0e-4,
    "turn_max_deg": 20.0,
    "descent_frac": 0.4,
    "amplitude_stop": 0.0,       # > 0: end every sweep here instead of past the folds
    "amplitude_max": 0.012,      # largest response amplitude (m)
    "beyond_fold": 0.2,          # go on to (1 + beyond_fold) x the jump-down fold amplitude
    "phi_max": 80.0,             # end a sweep once the sustaining forcing exceeds this, m/s^2
    "fold_margin": 0.02,
    "probe_min": 5.0e-6,         # smallest probe offset, m
    "fold_refine": 3,            # points bisecting towards a fold once it is passed
    "fold_gap": 0.01,            # ... until its neighbours are this close (relative)
    # convergence
    "max_picard": 8,
    "picard_from_control": True,
    "noninvasive_tol": 0.005,
    "noninvasive_sigmas": 2.0,
    "variance_rel": 0.004,
    "max_gate_polls": 4,
    "record_s": 0.25,
    # faults
    "max_fault_retries": 2,
    "max_fault_skips": 3,
    "max_restarts": 3,
    "rearm_ramp": 5,             # re-arm onto the last good target in this many steps
    "rearm_tries": 10,
    "rearm_fraction": 0.8,       # ... onto this fraction of it (the last good point may be
                                 # just under the trip level)
}

_KEY = re.compile(r"^f=([0-9.]+)/A=([0-9.]+)$")
TARGET_MAX = 0.0195   # target coefficients are limited to +-0.02 m by the register map
HIGHER = [0] + list(range(2, NH + 1)) + list(range(NH + 2, 2 * NH + 1))   # DC, harmonics 2..7


def point_key(f: float, A: float) -> str:
    return f"f={f:.3f}/A={A:.6f}"


def _zero_targets() -> dict:
    t = {"target_a0": 0.0}
    for k in range(1, NH + 1):
        t[f"target_a{k}"] = 0.0
        t[f"target_b{k}"] = 0.0
    return t


# ------------------------------------------------------------------------------ numbers
def invasiveness(coef, var=None, navg: int = 1) -> tuple[float, float, float]:
    """(residual, fundamental, standard error of the residual) of a control's 15
    coefficients: residual = norm of its DC and harmonics 2..7, fundamental =
    hypot(c1, s1); the standard error from the per-period variances (0 without)."""
    c = np.asarray(coef, dtype=float)
    resid = float(np.sqrt(np.sum(c[HIGHER] ** 2)))
    fund = float(math.hypot(c[1], c[1 + NH]))
    se = 0.0
    if var is not None:
        v = np.maximum(np.asarray(var, dtype=float)[HIGHER], 0.0)
        se = float(np.sqrt(np.sum(v) / max(navg, 1)))
    return resid, fund, se


def forcing_of(coef, var=None, navg: int = 1) -> tuple[float, float]:
    """(Phi, its standard error): the first-harmonic amplitude of an excitation."""
    e = np.asarray(coef, dtype=float)
    phi = float(math.hypot(e[1], e[1 + NH]))
    if var is None or phi <= 0:
        return phi, 0.0
    v = np.asarray(var, dtype=float)
    s2 = (e[1] ** 2 * max(v[1], 0.0) + e[1 + NH] ** 2 * max(v[1 + NH], 0.0)) / phi ** 2
    return phi, float(math.sqrt(s2 / max(navg, 1)))


def record_fourier(samples: dict | None, forcing_amplitude: float) -> dict | None:
    """Least-squares Fourier series (a0, a1..a7, b1..b7) over the recorded forcing
    phase of the response, the control and the total excitation (forcing
    ``parameter`` cos(phase) + control: exact for the amplitude of its fundamental
    when the host forcing is 0, and without actuator latency otherwise). None when
    there are too few samples."""
    if not samples or samples.get("x") is None or len(samples["x"]) < 8 * (2 * NH + 1):
        return None
    th = np.asarray(samples["phase"], dtype=float)
    B = np.empty((th.size, 2 * NH + 1))
    B[:, 0] = 1.0
    for k in range(1, NH + 1):
        B[:, k] = np.cos(k * th)
        B[:, k + NH] = np.sin(k * th)
    u = np.asarray(samples["control"], dtype=float)
    par = np.asarray(samples.get("parameter", np.zeros_like(u)), dtype=float)
    exc = u + (par * np.cos(th) if forcing_amplitude != 0 else 0.0)
    Y = np.column_stack([np.asarray(samples["x"], dtype=float), u, exc])
    coef, *_ = np.linalg.lstsq(B, Y, rcond=None)
    resid = Y - B @ coef
    # standard errors of the coefficients from the fit residual (white-noise model)
    dof = max(th.size - B.shape[1], 1)
    s2 = np.sum(resid ** 2, axis=0) / dof
    cov_diag = np.diag(np.linalg.inv(B.T @ B))
    out = {}
    for j, ch in enumerate(("response", "control", "excitation")):
        out[ch] = {"mean": coef[:, j], "var_of_mean": s2[j] * cov_diag}
    out["samples"] = int(th.size)
    return out


def controller_response(k: int, f: float, o: dict) -> complex:
    """The board's control law at harmonic k of f: u_k = C (target_k - x_k) for the
    complex coefficient a - i b; PD through the optional one-pole error filter
    (discrete, as the board runs it at `sample_rate`)."""
    w = 2 * math.pi * f * k
    C = o["kp"] + 1j * w * o["kd"]
    fc = o["filter_hz"]
    if fc > 0:
        dt = 1.0 / o["sample_rate"]
        a = 1.0 - math.exp(-2 * math.pi * fc * dt)
        C *= a / (1.0 - (1.0 - a) * complex(math.cos(w * dt), -math.sin(w * dt)))
    return C


def picard_update(T: np.ndarray, control, response, f: float, o: dict) -> np.ndarray:
    """One Picard step: DC and harmonics 2..7 of the target <- the response's.

    With ``picard_from_control`` (default) the response harmonics are read through
    the controller: x_k = T_k - u_k / C(k w), u_k the control's coefficient.
    That is the same quantity as the response channel's x_k, but the board's
    estimator leaks ~0.05 % of a signal's fundamental into each harmonic when a
    forcing period is not a whole number of samples; put into the target and
    multiplied by the controller's gain at the high harmonics (|C(7w)| ~ 5e4 1/s^2)
    that leak alone is a control residual of several per cent of the forcing at the
    jump-down fold. Through the control channel the leak is divided by |C| instead.
    """
    T = T.copy()
    r = np.asarray(response, dtype=float)
    if not o["picard_from_control"]:
        T[HIGHER] = r[HIGHER]
        return T
    u = np.asarray(control, dtype=float)
    T[0] = T[0] - u[0] / o["kp"] if o["kp"] != 0 else r[0]   # kp = 0: DC is not controlled
    for k in range(2, NH + 1):
        zx = complex(T[k], -T[k + NH]) - complex(u[k], -u[k + NH]) / controller_response(k, f, o)
        T[k], T[k + NH] = zx.real, -zx.imag
    return T


def _parabola(pts):
    """Coefficients (c2, c1, c0) of the parabola through three (A, Phi) points."""
    xs = [p[0] for p in pts]
    ys = [p[1] for p in pts]
    return np.polyfit(xs, ys, 2)


def slope_at_last(pts, sig) -> tuple[float, float]:
    """dPhi/dA at the last of (up to) three points from the parabola through them
    (the secant for two), and its standard error from the points' errors `sig`."""
    if len(pts) == 2:
        (x0, _), (x1, _) = pts
        w = np.array([-1.0, 1.0]) / (x1 - x0)
    else:
        (x0, _), (x1, _), (x2, _) = pts
        w = np.array([(x2 - x1) / ((x0 - x1) * (x0 - x2)),
                      (x2 - x0) / ((x1 - x0) * (x1 - x2)),
                      (2 * x2 - x0 - x1) / ((x2 - x0) * (x2 - x1))])
    y = np.array([p[1] for p in pts])
    return float(w @ y), float(np.sqrt(np.sum((w * np.asarray(sig)) ** 2)))


# ------------------------------------------------------------------------------ the sweep
class _Sweep:
    """The S-curve at one frequency: history, step control, fold bookkeeping."""

    def __init__(self, f: float, o: dict):
        self.f = float(f)
        self.o = o
        self.pts: list[tuple[float, float]] = [(0.0, 0.0)]   # (A, Phi), the origin first
        self.sig: list[float] = [0.0]
        self.labels: list[bool] = []
        self.targets_done: list[float] = []
        self.harm: list[tuple[float, np.ndarray]] = []       # (target, converged 15-vector)
        self.h = float(o["amplitude_step"])
        self.folds: list[dict] = []
        self.phase = 0                                       # folds confirmed so far
        self.ext_i = 0                                       # index of the running extreme
        self.extra: list[tuple[float, float]] = []          # fold-refinement points (A, Phi)
        self.armed = True                                    # False after a failed re-arm

    def predict_harmonics(self, A: float) -> np.ndarray:
        if not self.harm:
            return np.zeros(2 * NH + 1)
        if len(self.harm) == 1 or self.harm[-1][0] == self.harm[-2][0]:
            return self.harm[-1][1].copy()
        (A0, T0), (A1, T1) = self.harm[-2], self.harm[-1]
        w = max(min((A - A1) / (A1 - A0), 1.5), -1.0)       # no wild extrapolation
        return T1 + w * (T1 - T0)

    def settings(self, A: float, T: np.ndarray) -> dict:
        t = {"target_a0": float(T[0]), "target_a1": float(A), "target_b1": 0.0}
        for k in range(2, NH + 1):
            t[f"target_a{k}"] = float(T[k])
            t[f"target_b{k}"] = float(T[k + NH])
        return t

    def add(self, A_target: float, A: float, phi: float, sphi: float, T: np.ndarray):
        """Record a measured point; returns (dPhi/dA, its se, parabola curvature c2)."""
        self.pts.append((A, phi))
        self.sig.append(sphi)
        self.targets_done.append(A_target)
        self.harm.append((A_target, T.copy()))
        slope, se = slope_at_last(self.pts[-3:], self.sig[-3:])
        c2 = float(_parabola(self.pts[-3:])[0]) if len(self.pts) >= 3 else 0.0
        return slope, se, c2

    def update_folds(self):
        """Confirm folds with hysteresis; returns a new fold's record or None."""
        if self.phase >= 2 or len(self.pts) < 3:
            return None
        i = len(self.pts) - 1
        phi_i = self.pts[i][1]
        ext = self.pts[self.ext_i][1]
        margin = (self.o["fold_margin"] * max(ext, 1e-12)
                  + 3.0 * max(self.sig[i], self.sig[self.ext_i]))
        if self.phase == 0:
            if phi_i >= ext:
                self.ext_i = i
            elif phi_i < ext - margin:
                return self._confirm("jump-up")
        else:
            if phi_i <= ext:
                self.ext_i = i
            elif phi_i > ext + margin:
                return self._confirm("jump-down")
        return None

    def _confirm(self, kind: str) -> dict:
        j = self.ext_i
        # locate it among all points around the extreme, fold-refinement ones included
        lo = self.pts[j - 1][0] if j >= 1 else 0.0
        hi = self.pts[j + 1][0] if j + 1 < len(self.pts) else self.pts[j][0]
        pool = sorted({p for p in self.pts + self.extra if lo <= p[0] <= hi})
        pick = max if kind == "jump-up" else min
        m = pool.index(pick(pool, key=lambda p: p[1]))
        A_f, phi_f = pool[m]
        if 1 <= m < len(pool) - 1:
            # least-squares parabola over the points within 2 % of the extreme's
            # amplitude (at a flat fold three points leave the vertex to the noise),
            # at least the extreme and its two neighbours
            near = [p for p in pool if abs(p[0] - A_f) <= 0.02 * A_f]
            if len(near) < 3:
                near = pool[m - 1:m + 2]
            c2, c1, c0 = np.polyfit([p[0] for p in near], [p[1] for p in near], 2)
            if c2 != 0:
                Av = -c1 / (2 * c2)
                if pool[m - 1][0] <= Av <= pool[m + 1][0]:
                    A_f, phi_f = float(Av), float(np.polyval([c2, c1, c0], Av))
        fold = {"kind": kind, "amplitude": float(A_f), "parameter": float(phi_f),
                "frequency": self.f}
        self.folds.append(fold)
        self.phase += 1
        self.ext_i = len(self.pts) - 1
        return fold

    def finished(self, A_next: float) -> str:
        """Why the sweep ends before measuring at A_next ('' to go on)."""
        o = self.o
        phi_next = self.pts[-1][1]
        if len(self.pts) >= 3 and self.targets_done[-1] > self.targets_done[-2]:
            dT = self.targets_done[-1] - self.targets_done[-2]
            rate = (self.pts[-1][1] - self.pts[-2][1]) / dT
            phi_next += max(rate, 0.0) * (A_next - self.targets_done[-1])
        if len(self.pts) > 1 and phi_next > o["phi_max"]:
            return f"forcing would exceed phi_max ({phi_next:.1f} m/s^2 predicted)"
        if o["amplitude_stop"] > 0:
            if A_next > o["amplitude_stop"] + 1e-9:
                return "amplitude_stop reached"
        elif self.phase >= 2:
            # in measured amplitude (the target differs from it by |forcing / C(w)|)
            if self.pts[-1][0] >= (1 + o["beyond_fold"]) * self.folds[1]["amplitude"]:
                return "past both folds"
        # amplitude_max bounds the response; the target runs ahead of it by
        # |forcing / C(w)| (millimetres on the upper branch), so predict the response
        A_meas = self.pts[-1][0]
        if len(self.pts) >= 3 and self.targets_done[-1] > self.targets_done[-2]:
            dT = self.targets_done[-1] - self.targets_done[-2]
            gain = (self.pts[-1][0] - self.pts[-2][0]) / dT
            A_meas += max(gain, 0.0) * (A_next - self.targets_done[-1])
        if A_meas > o["amplitude_max"] + 1e-9:
            return "amplitude_max reached"
        if A_next > TARGET_MAX:
            return "target at the register's limit"
        return ""

    def next_step(self) -> float:
        """Adapt h after a point (turning angle, fold guards); returns it."""
        o = self.o
        h = self.h
        if len(self.pts) >= 3:
            Aref = max(p[0] for p in self.pts) or 1.0
            Pref = max(p[1] for p in self.pts) or 1.0
            (a0, p0), (a1, p1), (a2, p2) = [(a / Aref, p / Pref) for a, p in self.pts[-3:]]
            v1 = np.array([a1 - a0, p1 - p0])
            v2 = np.array([a2 - a1, p2 - p1])
            n = float(np.linalg.norm(v1) * np.linalg.norm(v2))
            if n > 0:
                ang = math.degrees(math.acos(max(-1.0, min(1.0, float(v1 @ v2) / n))))
                if ang > o["turn_max_deg"]:
                    h *= 0.5
                elif ang < o["turn_max_deg"] / 3:
                    h *= 1.5
        h = min(max(h, o["step_min"]), o["step_max"])
        if len(self.pts) >= 3 and self.phase < 2:
            (A1, P1), (A2, P2) = self.pts[-2:]
            # target and measured amplitude differ: scale the guards to target units
            ratio = (self.targets_done[-1] / A2) if A2 > 0 else 1.0
            sec = (P2 - P1) / (A2 - A1) if A2 != A1 else 0.0
            if sec < 0:                                 # falling: Phi must turn before 0
                h = min(h, max(o["step_min"], o["descent_frac"] * P2 / -sec * ratio))
            if len(self.pts) >= 4:
                c2, c1, _ = _parabola(self.pts[-3:])
                if c2 != 0:
                    Av = -c1 / (2 * c2)
                    if A2 < Av < A2 + h / ratio:        # a fold ahead within the step
                        h = max(o["step_min"], 0.5 * (Av - A2) * ratio)
        self.h = h
        return h


# ------------------------------------------------------------------------------ the plan
def oscillator_plan(config: dict):
    """Build the plan for an oscillator campaign from its (validated) config."""
    o0 = {**DEFAULTS, **config.get("cbc", {})}
    o0["navg"] = int(o0["navg"])
    freqs = [float(f) for f in config["frequencies"]]

    def plan(ctx):
        o = {**o0, "sample_rate": float((ctx.identity or {}).get("sample_rate", 10000.0))}
        state = {"index": len(ctx.previous or [])}
        summaries = _summaries(ctx)
        settings = {"kp": o["kp"], "kd": o["kd"], "navg": o["navg"], "phase_mode": 0,
                    "clamp": o["clamp"], "trip": o["trip"], "filter_hz": o["filter_hz"],
                    "forcing_amplitude": o["forcing_amplitude"], "frequency": freqs[0],
                    **_zero_targets()}
        try:
            yield Configure(settings)
        except (RigFault, RigRestarted):      # lost before it was written: once more
            yield Configure(settings)
        for f in freqs:
            yield from _run_sweep(_Sweep(f, o), o, ctx, summaries, state)
        try:
            yield Disarm()
        except (RigFault, RigRestarted):      # disarmed either way
            pass

    return plan


def _summaries(ctx) -> dict:
    """key -> (amplitude, parameter, stable or None) from ctx.previous, where given."""
    out = {}
    for p in ctx.previous or []:
        if isinstance(p, Mapping) and {"key", "amplitude", "parameter"} <= set(p):
            try:
                st = p.get("stable")
                out[str(p["key"])] = (float(p["amplitude"]), float(p["parameter"]),
                                      None if st is None else bool(st))
            except (TypeError, ValueError):
                continue
    return out


def _done_targets(ctx, f: float) -> list[float]:
    out = []
    for k in ctx.done or ():
        m = _KEY.match(str(k))
        if m and abs(float(m.group(1)) - f) < 5e-4:
            out.append(float(m.group(2)))
    return sorted(out)


def _run_sweep(s: _Sweep, o: dict, ctx, summaries: dict, state: dict):
    """Generator: the whole sweep at one frequency."""
    try:
        yield Configure({"frequency": s.f, "forcing_amplitude": o["forcing_amplitude"],
                         "phase_mode": 0, **_zero_targets()})
        yield Arm()
    except (RigFault, RigRestarted):
        s.armed = False                   # the first point re-arms (and re-configures)
        yield Configure({"frequency": s.f, "forcing_amplitude": o["forcing_amplitude"],
                         "phase_mode": 0, **_zero_targets()})
    done = ctx.done or set()
    replay = _done_targets(ctx, s.f)      # already in the file: rebuild the state only
    A = replay.pop(0) if replay else round(o["amplitude_start"], 6)
    prev_A = None                         # target of the last measured point
    last = None                           # its measurement
    skips = 0
    why = ""
    while True:
        key = point_key(s.f, A)
        if key in summaries and key in done:
            amp, phi, st = summaries[key]
            slope, _, _ = s.add(A, amp, phi, 0.0, s.predict_harmonics(A))
            s.labels.append(st if st is not None else slope > 0)
            s.update_folds()
            last = {"target": A, "amplitude": amp, "parameter": phi, "parameter_se": 0.0,
                    "harmonics": s.harm[-1][1]}
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
                slope, se, c2 = s.add(A, res["amplitude"], res["parameter"],
                                      res["parameter_se"], res["harmonics"])
                label = {"slope": slope, "slope_se": se, "method": "parabola", "probe": None}
                prev_label = s.labels[-1] if s.labels else True   # the origin: stable rest
                spacing = s.pts[-1][0] - s.pts[-2][0]
                near_vertex = c2 != 0 and abs(slope / (2 * c2)) < 0.5 * spacing
                if (slope > 0) != prev_label or abs(slope) <= 3 * se or near_vertex:
                    below = s.targets_done[-2] if len(s.targets_done) >= 2 else 0.0
                    probe = yield from _probe(s, o, res, c2, below)
                    if probe is not None:
                        label.update(probe)
                s.labels.append(label["slope"] > 0)
                if key not in done:
                    yield Emit("point", _point_doc(state["index"], key, s, res, o, label))
                    state["index"] += 1
                if last is not None and s.labels[-1] != s.labels[-2]:
                    # a fold between the last two points: close in on it
                    yield from _refine_fold(s, o, done, state, last, res)
                fold = s.update_folds()
                if fold is not None:
                    yield Emit("note", {"text": f"f = {s.f:g} Hz: {fold['kind']} fold near "
                                                f"A = {fold['amplitude'] * 1e3:.3f} mm, Phi = "
                                                f"{fold['parameter']:.3f} m/s^2", "fold": fold})
                last = res
                prev_A = A
        if replay:
            A = replay.pop(0)
            continue
        h = s.next_step()
        A = round((prev_A if prev_A is not None else A) + h, 6)
        why = s.finished(A)
        if why:
            break
    yield Emit("note", {"text": f"f = {s.f:g} Hz: sweep ended ({why}); "
                                f"{len(s.pts) - 1} points, {len(s.folds)} folds",
                        "folds": s.folds})


def _refine_fold(s: _Sweep, o: dict, done, state: dict, lo: dict, hi: dict):
    """Generator: bisect (in target amplitude) between two points whose labels differ
    until they are less than ``fold_gap`` of the amplitude apart (at most
    ``fold_refine`` points). Each new point is labelled by its own probe (the
    secant just below it), emitted, and kept for locating the fold."""
    lab_lo = s.labels[-2]
    for _ in range(int(o["fold_refine"])):
        if hi["amplitude"] - lo["amplitude"] <= o["fold_gap"] * hi["amplitude"]:
            return
        T = round(0.5 * (lo["target"] + hi["target"]), 6)
        key = point_key(s.f, T)
        if not lo["target"] < T < hi["target"] or key in done:
            return
        res = yield from _attempt(s, o, T, lo["target"],
                                  start=0.5 * (lo["harmonics"] + hi["harmonics"]))
        if res is None:
            return
        T = res["target"]
        key = point_key(s.f, T)
        trio = [(lo["amplitude"], lo["parameter"]), (res["amplitude"], res["parameter"]),
                (hi["amplitude"], hi["parameter"])]
        c2 = float(_parabola(trio)[0])
        slope, se = _centred_slope(trio, [lo["parameter_se"], res["parameter_se"],
                                          hi["parameter_se"]])
        label = {"slope": slope, "slope_se": se, "method": "centred parabola", "probe": None,
                 "refinement": True}
        probe = yield from _probe(s, o, res, c2, lo["target"])
        if probe is not None:
            label.update(probe)
        s.extra.append((res["amplitude"], res["parameter"]))
        if key not in done:
            yield Emit("point", _point_doc(state["index"], key, s, res, o, label))
            state["index"] += 1
        if (label["slope"] > 0) == lab_lo:
            lo = res
        else:
            hi = res


def _centred_slope(trio, sig) -> tuple[float, float]:
    """dPhi/dA at the middle of three points (parabola) and its standard error."""
    (x0, _), (x1, _), (x2, _) = trio
    w = np.array([(x1 - x2) / ((x0 - x1) * (x0 - x2)),
                  (2 * x1 - x0 - x2) / ((x1 - x0) * (x1 - x2)),
                  (x1 - x0) / ((x2 - x0) * (x2 - x1))])
    y = np.array([p[1] for p in trio])
    return float(w @ y), float(np.sqrt(np.sum((w * np.asarray(sig)) ** 2)))


def _probe(s: _Sweep, o: dict, res: dict, c2: float, prev: float):
    """Generator: the local slope just below a point whose label is in doubt (the
    probe stays above the target `prev` of the point below it). Returns
    {"slope", "slope_se", "method", "probe"} or None if the probe failed."""
    A = res["target"]
    sig = max(res["parameter_se"], 1e-12)
    eps = math.sqrt(2 * math.sqrt(2) * sig / max(abs(2 * c2), 1e-300)) if c2 else 0.5 * (A - prev)
    eps = min(max(eps, o["probe_min"]), 0.5 * (A - prev))
    Ap = round(A - eps, 7)
    if Ap <= prev or Ap <= 0:
        return None
    try:
        pr = yield from _measure(s, o, Ap, start=res["harmonics"])
    except (RigFault, RigRestarted) as exc:
        yield Emit("note", {"text": f"f = {s.f:g} Hz: probe at {Ap * 1e3:.4f} mm lost ({exc})"})
        yield from _rearm(s, o, prev if prev > 0 else None)
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


def _attempt(s: _Sweep, o: dict, A: float, prev_A, start=None):
    """Generator: measure the point at target A, handling faults and restarts.
    Returns the measurement dict or None (skipped)."""
    faults = 0
    restarts = 0
    if not s.armed:
        if not (yield from _rearm(s, o, prev_A)):
            return None
    while True:
        try:
            return (yield from _measure(s, o, A, start=start))
        except RigRestarted:
            restarts += 1
            yield Emit("note", {"text": f"f = {s.f:g} Hz, A = {A * 1e3:.3f} mm: link lost; "
                                        "point repeated"})
            if restarts > o["max_restarts"] or not (yield from _rearm(s, o, None)):
                return None
        except RigFault as exc:
            faults += 1
            base = prev_A if prev_A is not None else 0.0
            new_A = round(base + 0.5 * (A - base), 6)
            if prev_A is None or faults > o["max_fault_retries"] or new_A - base < o["step_min"]:
                yield Emit("note", {"text": f"f = {s.f:g} Hz: {exc} at target A = "
                                            f"{A * 1e3:.3f} mm; target skipped"})
                yield from _rearm(s, o, prev_A)
                return None
            yield Emit("note", {"text": f"f = {s.f:g} Hz: {exc} at target A = {A * 1e3:.3f} mm; "
                                        f"retrying at {new_A * 1e3:.3f} mm"})
            A = new_A
            s.h = max(o["step_min"], new_A - base)
            if not (yield from _rearm(s, o, prev_A)):
                return None


def _rearm(s: _Sweep, o: dict, back_to: float | None):
    """Generator: arm again after a fault or a reconnect; True once armed. With
    `back_to`, first on ``rearm_fraction`` of the target of that (last good) point
    (which may lie just under the trip level), ramped up from rest in
    ``rearm_ramp`` steps, waiting for the rig to settle there: a PD loop (damping
    ratio ~0.2 here) jumping from rest straight onto a large target overshoots it
    by half and can trip again. Three tries; after that `s.armed` stays False and the next
    point tries again before it measures anything."""
    s.armed = False
    for _ in range(int(o["rearm_tries"])):
        try:
            # disarmed, the structure rings down on its own first (a trip latches
            # again while it still swings past the trip level: that is a retry);
            # the Configure also restarts the engine's period count for the Settle
            yield Configure(_zero_targets())
            yield Settle(periods=int(o["transient_periods"]))
            if back_to is not None:
                T = s.harm[-1][1] if s.harm else np.zeros(2 * NH + 1)
                n = max(int(o["rearm_ramp"]), 1)
                top = o["rearm_fraction"] * back_to
                yield Configure(s.settings(top / n, T / n))
                yield Arm()
                for k in range(2, n + 1):          # ramp up: a jump from rest overshoots
                    yield Settle(periods=int(o["transient_periods"]))
                    yield Configure(s.settings(top * k / n, T * k / n))
                yield Settle(periods=int(o["transient_periods"]) + o["navg"])
            else:
                yield Arm()
            s.armed = True
            return True
        except (RigFault, RigRestarted):
            continue
    yield Emit("note", {"text": f"f = {s.f:g} Hz: the rig could not be re-armed "
                                f"({int(o['rearm_tries'])} tries)"})
    return False


def _measure(s: _Sweep, o: dict, A: float, start=None):
    """Generator: Picard iteration, variance gate and record at target amplitude A.
    When the record's fit still finds the control invasive, Picard goes on from it
    (within ``max_picard`` iterations in all) and the point is recorded again."""
    navg = o["navg"]
    t_wall = time.time()
    T = s.predict_harmonics(A) if start is None else np.array(start, dtype=float)
    rows = []
    iters = 0
    rig_s = 0.0
    while True:
        est = None
        while iters < int(o["max_picard"]) or est is None:
            yield Configure(s.settings(A, T))
            est = yield Settle(periods=int(o["transient_periods"]) + navg)
            iters += 1
            rig_s += est.waited_s
            resid, fund, se = invasiveness(est.fourier["control"]["mean"],
                                           est.fourier["control"]["var"], navg)
            rows.append(_row(len(rows), "picard", A, est, resid, fund, se))
            if resid <= max(o["noninvasive_tol"] * fund, o["noninvasive_sigmas"] * se):
                break
            T = picard_update(T, est.fourier["control"]["mean"], est.fourier["response"]["mean"],
                              s.f, o)
        gate_ok = _gate(est, o)
        for _ in range(int(o["max_gate_polls"])):
            if gate_ok:
                break
            yield Configure(s.settings(A, T))
            est = yield Settle(periods=navg)
            rig_s += est.waited_s
            resid, fund, se = invasiveness(est.fourier["control"]["mean"],
                                           est.fourier["control"]["var"], navg)
            rows.append(_row(len(rows), "gate", A, est, resid, fund, se))
            gate_ok = _gate(est, o)
        if o["record_s"] > 0:        # the estimate read after it covers its last navg periods
            est = yield Settle(periods=0, record_s=float(o["record_s"]))
            rig_s += est.waited_s
            gate_ok = _gate(est, o)
        resid, fund, se = invasiveness(est.fourier["control"]["mean"],
                                       est.fourier["control"]["var"], navg)
        phi, sphi = forcing_of(est.fourier["excitation"]["mean"], est.fourier["excitation"]["var"],
                               navg)
        amp = amplitude(est.fourier["response"]["mean"])
        fit = record_fourier(est.samples, o["forcing_amplitude"])
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
        noninvasive = resid <= max(o["noninvasive_tol"] * fund, o["noninvasive_sigmas"] * se)
        if noninvasive or iters >= int(o["max_picard"]) or fit is None:
            break
        T = picard_update(T, fit["control"]["mean"], fit["response"]["mean"], s.f, o)
    return {"target": A, "estimate": est, "fit": fit, "source": source, "amplitude": amp,
            "parameter": phi, "parameter_se": sphi, "harmonics": T, "noninvasive": noninvasive,
            "gate": gate_ok, "residual": resid, "fundamental": fund, "residual_se": se,
            "picard": iters, "history": rows, "rig_seconds": rig_s,
            "wall_s": time.time() - t_wall}


def _gate(est, o) -> bool:
    r = est.fourier["response"]
    A1 = amplitude(r["mean"])
    spread = math.sqrt(max(r["var"][1], 0.0) + max(r["var"][1 + NH], 0.0))
    return math.isfinite(est.frequency) and spread <= o["variance_rel"] * max(A1, 1e-9)


def _row(i, stage, A, est, resid, fund, se) -> dict:
    phi, _ = forcing_of(est.fourier["excitation"]["mean"])
    return {"iteration": i, "stage": stage, "target_amplitude": A,
            "amplitude": amplitude(est.fourier["response"]["mean"]), "parameter": phi,
            "control_residual": resid, "control_fundamental": fund, "residual_se": se,
            "invasiveness": resid / fund if fund > 0 else float("inf"),
            "frequency": est.frequency, "rig_time": est.rig_time, "waited_s": est.waited_s}


def _point_doc(index, key, s: _Sweep, res: dict, o: dict, label: dict) -> dict:
    est = res["estimate"]
    resp = np.asarray(est.fourier["response"]["mean"])
    ts = est.samples or {}
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
    if ts.get("x") is not None and len(ts["x"]):
        extra["control_rms"] = float(np.sqrt(np.mean(np.asarray(ts["control"]) ** 2)))
        extra["response_rms"] = float(np.sqrt(np.mean((np.asarray(ts["x"]) - coef[0]) ** 2)))
        extra["gap_records"] = int(ts.get("gap_records", 0))
    timeseries = {k: np.asarray(v) for k, v in ts.items() if k != "gap_records"}
    settings = {"kp": o["kp"], "kd": o["kd"], "filter_hz": o["filter_hz"], "navg": o["navg"],
                "frequency": s.f, "forcing_amplitude": o["forcing_amplitude"], "phase_mode": 0,
                **s.settings(res["target"], res["harmonics"])}
    return {
        "index": index, "key": key, "rig": "oscillator", "parameter": float(res["parameter"]),
        "parameter_name": "forcing_amplitude", "frequency": float(s.f),
        "amplitude": float(res["amplitude"]), "stable": bool(label["slope"] > 0),
        "stability_method": STABILITY_METHOD,
        "status": "ok" if (res["noninvasive"] and res["gate"]) else "not_converged",
        "settings": settings,
        "fourier": {ch: {"mean": np.asarray(v["mean"]), "var": np.asarray(v["var"])}
                    for ch, v in est.fourier.items()},
        "history": res["history"], "rig_time": est.rig_time, "wall_time": res["wall_s"],
        "timeseries": timeseries, "extra": extra,
    }
