"""CBC for the autonomous aerofoil: limit cycles at fixed airspeeds.

The board's target is phase-locked to the response, x* = A0 + A1* cos(phi). For a
target amplitude A1* the controlled rig settles on an orbit of amplitude A1; the
open-loop limit cycles are the roots of e(A1*) = A1* - A1 (the control's
fundamental vanishes there). At each airspeed the plan
  1. scans A1* upward on a grid (starting near the previous airspeed's roots),
  2. brackets each sign change of e and refines it by regula falsi (Illinois),
  3. at every evaluation runs Picard iteration on the DC target (A0 <- measured DC)
     and the phase-lock frequency (f <- measured frequency) and waits for the
     board's variance gate,
as the wind-tunnel campaign did (Lee et al. 2020). The method is the "bracketing
search on the target amplitude at fixed airspeed" of DESIGN.md.

Stability of a root from the sign of de/dA1*: the control is proportional in the
amplitude error, so where the open-loop amplitude would decay (inside the
unstable cycle and outside the stable one) the controlled response falls short
of the target (e > 0), and where it would grow it overshoots (e < 0). A root where
e goes from + to - with A1* is therefore an unstable cycle, from - to + a stable one.
"""

from __future__ import annotations

import math
import time

import numpy as np

from ..engine import amplitude
from ..messages import Arm, Configure, Disarm, Emit, RigFault, RigRestarted, Settle

STABILITY_METHOD = "sign of de/dA* at the root (e = target amplitude - response amplitude)"

DEFAULTS = {
    "kp": 200.0, "kd": 60.0, "navg": 6, "transient_periods": 2, "frequency_guess": 2.4,
    "amplitude_min": 0.006, "amplitude_max": 0.14, "amplitude_step": 0.012,
    "tolerance_abs": 2e-5, "tolerance_rel": 1e-3, "frequency_tolerance": 0.002,
    "dc_tolerance": 5e-5, "max_picard": 8, "max_refine": 16, "variance_rel": 5e-3,
    "max_gate_polls": 4, "record_s": 2.0, "clamp": 300.0, "trip": 0.2,
    "picard_harmonics": False, "max_faults": 3, "noisy_fit": False,
    "noise_tolerance": 0.0, "quench_periods": 6, "max_quench": 8,
}


def _targets(a0: float, a1: float) -> dict:
    t = {f"target_a{k}": 0.0 for k in range(1, 8)}
    t.update({f"target_b{k}": 0.0 for k in range(1, 8)})
    t["target_a0"] = a0
    t["target_a1"] = a1
    return t


class _Search:
    """State of the search at one airspeed."""

    def __init__(self, V, o):
        self.V = V
        self.o = o
        self.a0 = 0.0
        self.harmonics = np.zeros(15)     # Picard-iterated target harmonics 2..7 (a and b)
        self.f = o["frequency_guess"]
        self.history: list[dict] = []
        self.roots_emitted: list[dict] = []
        self.emit_root = None
        self.evals: dict[float, tuple] = {}
        self.t_wall = time.time()

    def evaluate(self, A, quick: bool = False):
        """Generator: Picard on DC and frequency at target amplitude A, then the
        variance gate. Returns (e, estimate) or (None, estimate) if no cycle formed.
        `quick` (scanning: only the sign of e matters) stops after one Picard round
        unless e is within a few tolerances of zero."""
        o = self.o
        est = None
        A1_prev = None
        tol = max(o["tolerance_abs"], o["tolerance_rel"] * A)
        for it in range(o["max_picard"]):
            yield Configure({**self.targets(A), "frequency": self.f})
            est = yield Settle(periods=o["navg"] + o["transient_periods"])
            if not math.isfinite(est.frequency) or est.frequency <= 0:
                self.history.append(self._row(A, est, float("nan"), it))
                return None, est
            resp = est.fourier["response"]["mean"]
            d_a0 = abs(resp[0] - self.a0)
            d_f = abs(est.frequency - self.f)
            self.a0 = float(resp[0])
            self.f = float(min(max(est.frequency, 0.2), 19.0))
            if o["picard_harmonics"]:
                # higher harmonics of the target follow the response's, so the control
                # has none: only its fundamental (the root condition) remains
                for k in list(range(2, 8)) + list(range(9, 15)):
                    self.harmonics[k] = float(resp[k])
            A1 = amplitude(resp)
            self.history.append(self._row(A, est, A - A1, it))
            if quick and abs(A - A1) > 0.1 * A:
                break                     # far from a root: the sign of e is all we need
            # steady when the Picard variables have stopped moving AND the amplitude has
            # (the DC and the amplitude settle on the slow time scale of the closed loop)
            if (d_a0 < o["dc_tolerance"] and d_f < o["frequency_tolerance"]
                    and A1_prev is not None and abs(A1 - A1_prev) < 0.5 * tol):
                break
            A1_prev = A1
        for _ in range(o["max_gate_polls"]):          # variance gate on the fundamental
            var = est.fourier["response"]["var"]
            A1 = amplitude(est.fourier["response"]["mean"])
            spread = math.sqrt(max(var[1], 0.0) + max(var[8], 0.0))
            if spread <= o["variance_rel"] * max(A1, 1e-6):
                break
            est = yield Settle(periods=o["navg"])
        A1 = amplitude(est.fourier["response"]["mean"])
        e = A - A1
        self.evals[A] = (e, est)
        return e, est

    def targets(self, A) -> dict:
        t = _targets(self.a0, A)
        for k in range(2, 8):
            t[f"target_a{k}"] = self.harmonics[k]
            t[f"target_b{k}"] = self.harmonics[k + 7]
        return t

    def _row(self, A, est, e, it):
        return {"iteration": len(self.history), "picard": it, "target_amplitude": A,
                "amplitude": amplitude(est.fourier["response"]["mean"]), "error": e,
                "frequency": est.frequency, "dc": float(est.fourier["response"]["mean"][0]),
                "rig_time": est.rig_time}


def flutter_plan(config: dict):
    """Build the plan for a flutter campaign from its (validated) config."""
    o = {**DEFAULTS, **config.get("cbc", {})}
    airspeeds = list(config["parameter"]["values"])

    def plan(ctx):
        yield Configure({"kp": o["kp"], "kd": o["kd"], "navg": int(o["navg"]), "phase_mode": 1,
                         "clamp": o["clamp"], "trip": o["trip"], "airspeed": airspeeds[0],
                         "frequency": o["frequency_guess"], **_targets(0.0, 0.0)})
        counter = {"index": len(ctx.previous)}
        faults_in_a_row = 0
        for V in airspeeds:
            keys = [k for k in ctx.done if k.startswith(f"V={V:.4f}/")]
            if keys and len(keys) >= 2:
                continue                                 # this airspeed is in the file
            for attempt in range(3):
                s = _Search(V, o)
                s.emit_root = _root_emitter(ctx, counter, s, o)
                try:
                    yield from _search_airspeed(s, o)      # emits each root as it is found
                    faults_in_a_row = 0
                    break
                except RigRestarted as exc:
                    yield Emit("note", {"text": f"V = {V}: link lost ({exc}); the airspeed is "
                                                "repeated", "interrupted": f"V={V:.4f}"})
                except RigFault as exc:
                    faults_in_a_row += 1
                    yield Emit("note", {"text": f"V = {V}: {exc}; the rest of this airspeed is "
                                                "abandoned", "interrupted": f"V={V:.4f}"})
                    break
            if faults_in_a_row >= o["max_faults"]:
                yield Emit("note", {"text": f"{faults_in_a_row} faults in a row: campaign stopped"})
                break
        yield Disarm()

    return plan


def _root_emitter(ctx, counter, s, o):
    """Generator factory: the Emit for a refined root (skipped if already logged)."""
    def emit(r):
        # keyed by kind, not by order: a root missed once must not rename the others
        kind = "stable" if r["stable"] else "unstable"
        k = sum(1 for x in s.roots_emitted if x["stable"] == r["stable"])
        s.roots_emitted.append(r)
        key = f"V={s.V:.4f}/{kind}{k}"
        if key in ctx.done:
            return None
        msg = Emit("point", _point_doc(counter["index"], key, s, r, o))
        counter["index"] += 1
        return msg
    return emit


def _search_airspeed(s: _Search, o: dict):
    """Generator: find, refine and emit the roots of e(A) at s.V; returns them.

    The scan goes upward from a small target amplitude, from rest, and refines each
    bracket as soon as it appears, so the target never jumps far below the orbit the
    rig is on (a phase-locked target needs the orbit to encircle its centre). The
    scan ends at the stable cycle (beyond it e only grows: the model has no further
    cycle there).
    """
    yield Configure({"airspeed": s.V})
    yield from _quench(o)
    s.a0 = 0.0
    yield Configure({"phase_mode": 1, **_targets(0.0, 0.0)})
    yield Arm()
    step = o["amplitude_step"]
    grid = sorted(np.round(np.arange(o["amplitude_min"], o["amplitude_max"] + 1e-12, step), 6))
    roots: list = []
    yield from _scan(s, o, grid, roots)
    yield Disarm()
    return roots


def _scan(s: _Search, o: dict, grid: list, roots: list):
    """Generator: evaluate e on an ascending grid, refining each sign change on the
    way; returns True once the stable cycle has been found."""
    last = None
    below = None                      # the grid point before `last`
    for A in grid:
        e, _ = yield from s.evaluate(A, quick=True)
        if e is None:
            last = below = None
            continue
        if last is not None and last[1] * e < 0:
            # a quick evaluation can catch a transient: confirm the sign change at
            # steady state before spending a refinement on it
            lo, hi = last[0], A
            e_lo, _ = yield from s.evaluate(lo)
            e, _ = yield from s.evaluate(A)
            if e is not None and e_lo is not None and e_lo * e > 0 and below is not None:
                # the quick value at `lo` was the transient (the response still catching
                # up from below): at steady state the sign changes one step lower
                e_below, _ = yield from s.evaluate(below[0])
                if e_below is not None and e_below * e_lo < 0:
                    lo, hi, e = below[0], lo, e_lo
                    e_lo = e_below
            if e is not None and e_lo is not None and e_lo * e < 0:
                r = yield from _refine(s, o, lo, hi)
                if r is not None and r["converged"]:
                    roots.append(r)
                    msg = s.emit_root(r) if s.emit_root else None
                    if msg is not None:
                        yield msg                  # logged now: a later fault cannot lose it
                    if r["stable"]:
                        return True
                elif r is not None:
                    yield Emit("note", {"text": f"V = {s.V}: no converged cycle in "
                                                f"[{lo:.4f}, {hi:.4f}] m (final error "
                                                f"{r['error']:.2e} m); not logged as a point"})
                e, _ = yield from s.evaluate(A, quick=True)   # back above the root, go on
        below = last
        last = (A, e) if e is not None else None
    return False


def _quench(o: dict):
    """Bring the aerofoil to rest: a zero target on the forcing phase is plain PD
    damping of the heave. Needed because the rig is bistable: without it an airspeed
    would start on the last airspeed's stable cycle."""
    yield Configure({"phase_mode": 0, **_targets(0.0, 0.0)})
    yield Arm()
    for _ in range(o["max_quench"]):
        est = yield Settle(periods=o["quench_periods"])
        if amplitude(est.fourier["response"]["mean"]) < 0.25 * o["amplitude_min"]:
            break


def _refine(s: _Search, o: dict, lo: float, hi: float):
    """Regula falsi (Illinois) on e(A*) inside [lo, hi], falling back to bisection
    whenever an iteration fails to halve the bracket; then the root's record."""
    elo, ehi = s.evals[lo][0], s.evals[hi][0]
    if elo * ehi >= 0:
        return None
    decreasing = elo > 0 > ehi
    slope = (ehi - elo) / (hi - lo)               # from measured values, never the halved ones
    if o["noisy_fit"]:
        A, slope = yield from _fit_root(s, o, lo, hi, decreasing)
        if A is None:
            return None
        return (yield from _record_root(s, o, A, slope, decreasing))
    flo, fhi = elo, ehi                           # Illinois' working values
    side, bisect = 0, False
    A = lo
    for _ in range(o["max_refine"]):
        width = hi - lo
        A = 0.5 * (lo + hi) if bisect else hi - fhi * (hi - lo) / (fhi - flo)
        e, est = yield from s.evaluate(A)
        if e is None:
            return None
        tol = max(o["tolerance_abs"], o["tolerance_rel"] * A)
        if (e > 0) == (elo > 0):
            lo, elo, flo = A, e, e
            if side == -1:
                fhi /= 2
            side = -1
        else:
            hi, ehi, fhi = A, e, e
            if side == 1:
                flo /= 2
            side = 1
        slope = (ehi - elo) / (hi - lo)
        # the root's location in A* is what matters: near the Hopf point e is shallow
        # (|de/dA*| << 1), so a small |e| alone can leave A* far from the root
        if abs(e) <= 0.2 * tol * abs(slope):
            break
        if (hi - lo) <= 2 * tol:
            A = hi - ehi * (hi - lo) / (ehi - elo)     # the root inside the final bracket
            break
        bisect = (hi - lo) > 0.5 * width
    return (yield from _record_root(s, o, A, slope, decreasing))


def _record_root(s: _Search, o: dict, A: float, slope: float, decreasing: bool = True):
    """Converge fully at the root's target, then log the full-rate time series; if the
    orbit drifted (an unstable cycle held by a marginal loop), again."""
    tol = max(o["tolerance_abs"], o["tolerance_rel"] * A)
    ok = False
    e, est = None, None
    for _ in range(3):
        e, est = yield from s.evaluate(A)
        if e is None:
            return None
        yield Configure({**s.targets(A), "frequency": s.f})
        est = yield Settle(periods=o["navg"], record_s=o["record_s"])
        e = A - amplitude(est.fourier["response"]["mean"])
        # accepted only if the recorded orbit itself satisfies the root condition, to
        # within the tolerance on the root's location (|e| / |de/dA*|, local slope)
        ok = abs(e) <= max(2 * tol, o["noise_tolerance"]) * max(abs(slope), 0.05)
        if ok:
            break
    return {"target": A, "error": e, "estimate": est, "stable": not decreasing, "converged": ok}


def _fit_root(s: _Search, o: dict, lo: float, hi: float, decreasing: bool):
    """Experimental (cbc.noisy_fit, off by default; not yet better than regula falsi at
    sigma = 0.02). With process noise single values of e are unreliable near the root: fit a line
    through e on a grid across the bracket, then on a finer one around the fitted root
    (the paper's surrogate, locally), and return the root and the slope."""
    pts = []
    for A in np.linspace(lo, hi, 5):
        e, _ = yield from s.evaluate(float(A))
        if e is not None:
            pts.append((float(A), e))
    root, slope = _line_root(pts, lo, hi)
    if root is None:
        return None, slope
    w = 0.25 * (hi - lo)
    for A in (root - 0.5 * w, root, root + 0.5 * w):
        e, _ = yield from s.evaluate(float(A))
        if e is not None:
            pts.append((float(A), e))
    near = [(a, e) for a, e in pts if abs(a - root) <= w]
    root2, slope2 = _line_root(near if len(near) >= 3 else pts, lo, hi)
    if root2 is None or (slope2 < 0) != decreasing:
        return root, slope
    return root2, slope2


def _line_root(pts, lo, hi):
    if len(pts) < 2:
        return None, 0.0
    a, e = np.array(pts).T
    slope, icpt = np.polyfit(a, e, 1)
    if slope == 0:
        return None, 0.0
    root = -icpt / slope
    return (float(root), float(slope)) if lo <= root <= hi else (None, float(slope))


def _point_doc(index, key, s: _Search, r: dict, o: dict) -> dict:
    est = r["estimate"]
    resp = est.fourier["response"]["mean"]
    ts = est.samples or {}
    extra = {"target_amplitude": r["target"], "final_error": r["error"],
             "dc": float(resp[0]), "evaluations": len(s.history)}
    if ts.get("x") is not None and len(ts["x"]):
        extra["control_rms"] = float(np.sqrt(np.mean(ts["control"] ** 2)))
        extra["response_rms"] = float(np.sqrt(np.mean((ts["x"] - resp[0]) ** 2)))
        extra["gap_records"] = int(ts.get("gap_records", 0))
    timeseries = {k: np.asarray(v) for k, v in ts.items() if k != "gap_records"}
    settings = {"kp": o["kp"], "kd": o["kd"], "airspeed": s.V, "frequency": s.f,
                "navg": o["navg"], **s.targets(r["target"])}
    return {
        "index": index, "key": key, "rig": "flutter", "parameter": float(s.V),
        "parameter_name": "airspeed", "frequency": float(est.frequency),
        "amplitude": amplitude(resp), "stable": bool(r["stable"]),
        "stability_method": STABILITY_METHOD,
        "status": "ok" if r["converged"] else "not_converged",
        "settings": settings,
        "fourier": {ch: {"mean": np.asarray(v["mean"]), "var": np.asarray(v["var"])}
                    for ch, v in est.fourier.items()},
        "history": s.history, "rig_time": est.rig_time, "wall_time": time.time() - s.t_wall,
        "timeseries": timeseries, "extra": extra,
    }
