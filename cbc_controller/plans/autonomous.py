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

Under process noise (cbc.root_method = "regression") one estimate of e scatters by
a few per cent of the amplitude however close the search is, so regula falsi
would converge onto the noise. There every evaluation keeps the board's
consecutive navg-period blocks as repeated measurements of e, a sign is trusted
only when it stands out of their scatter, and a bracket is refined by probing on
both sides of the current root and fitting a line through all the blocks near it
(regression_root) until the root's standard error is small. The point's amplitude
is then the regression's fixed point (A1 = A* where e = 0), which averages every
block, rather than the last block alone.

Each airspeed is a segment: it starts with the rig at rest and its noise streams seeded
from the campaign's seed and the airspeed (`Reseed`, lockstep rigs). An airspeed with
both its cycles in the file is skipped on resume; any other is measured again from its
start, emitting the cycles the file lacks: the same numbers as without the interruption.

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

from ..harmonics import amplitude
from ..messages import Arm, Configure, Disarm, Emit, RigFault, RigRestarted, Settle
from ._steps import PointLog, configure_and_settle, point_doc, start_segment
from .bracket import Bracket
from .options import FlutterOptions
from .regression_root import pooled_sd, root_from_blocks

STABILITY_METHOD = "sign of de/dA* at the root (e = target amplitude - response amplitude)"

DEFAULTS = FlutterOptions().as_dict()     # the options' defaults, as a table


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
        self.f = o.frequency_guess
        self.history: list[dict] = []
        self.roots_emitted: list[dict] = []
        self.emit_root = None
        self.evals: dict[float, tuple] = {}
        self.blocks: dict[float, list] = {}   # regression: steady blocks of e per target
        self.settled: set = set()             # targets whose sign of e is known at steady state
        self.last_target = None
        self.t_wall = time.time()
        self.found: list = []                 # (airspeed, stable, target) found before

    def evaluate(self, A, quick: bool = False, sign_only: bool = False, coarse: bool = False):
        """Generator: Picard on DC and frequency at target amplitude A, then the
        variance gate. Returns (e, estimate) or (None, estimate) if no cycle formed.
        `quick` (scanning: only the sign of e matters) stops after one Picard round
        unless e is within a few tolerances of zero. `sign_only` (confirming a sign
        change at steady state) stops once the amplitude's last move is too small
        for the rest of its geometric relaxation to change the sign of e; a target
        whose sign is settled that way, by any evaluation, is in `self.settled`.
        `coarse` (a refinement step far from the root, which only places the next
        step) stops once e is known to a few per cent."""
        o = self.o
        if o.root_method == "regression":
            return (yield from self._evaluate_blocks(A, quick))
        est = None
        A1_prev = None
        self.settled.discard(A)
        tol = max(o.tolerance_abs, o.tolerance_rel * A)
        for it in range(o.max_picard):
            est = yield from configure_and_settle({**self.targets(A), "frequency": self.f},
                                                  o.navg + o.transient_periods)
            if not math.isfinite(est.frequency) or est.frequency <= 0:
                self.history.append(self._row(A, est, float("nan"), it))
                return None, est
            resp = est.fourier["response"]["mean"]
            d_a0 = abs(resp[0] - self.a0)
            d_f = abs(est.frequency - self.f)
            A1 = self._picard(est)
            self.history.append(self._row(A, est, A - A1, it))
            # far from a root the sign of e is all a scan needs, but the first round
            # after a step up can still be lagging (e > 0 however the orbit ends up)
            if quick and abs(A - A1) > 0.1 * A and (it > 0 or A1 > A):
                break
            moved = abs(A1 - A1_prev) if A1_prev is not None else math.inf
            if abs(A - A1) > 4 * moved:
                self.settled.add(A)
                if sign_only:
                    break
            if coarse and abs(A - A1) > 10 * tol and moved < 0.05 * abs(A - A1):
                break
            # steady when the Picard variables have stopped moving AND the amplitude has
            # (the DC and the amplitude settle on the slow time scale of the closed loop)
            if (d_a0 < o.dc_tolerance and d_f < o.frequency_tolerance
                    and moved < 0.5 * tol):
                self.settled.add(A)
                break
            A1_prev = A1
        for _ in range(o.max_gate_polls):          # variance gate on the fundamental
            var = est.fourier["response"]["var"]
            A1 = amplitude(est.fourier["response"]["mean"])
            spread = math.sqrt(max(var[1], 0.0) + max(var[8], 0.0))
            if spread <= o.variance_rel * max(A1, 1e-6):
                break
            est = yield Settle(periods=o.navg)
        A1 = amplitude(est.fourier["response"]["mean"])
        e = A - A1
        self.evals[A] = (e, est)
        return e, est

    def _picard(self, est) -> float:
        """One Picard step: the DC target and the phase-lock frequency (and, if asked,
        the higher target harmonics) follow the response; returns its amplitude."""
        resp = est.fourier["response"]["mean"]
        self.a0 = float(resp[0])
        self.f = float(min(max(est.frequency, 0.2), 19.0))
        if self.o.picard_harmonics:
            # higher harmonics of the target follow the response's, so the control
            # has none: only its fundamental (the root condition) remains
            for k in list(range(2, 8)) + list(range(9, 15)):
                self.harmonics[k] = float(resp[k])
        return amplitude(resp)

    def _evaluate_blocks(self, A, quick: bool):
        """Generator (root_method = "regression"): e at target A as the mean of
        consecutive navg-period blocks, Picard running on between blocks. The first
        block after a new target holds the closed loop's transient and only serves a
        quick scan far from any root; the steady ones are kept for the regression.
        A quick evaluation stops once the sign of e stands out of the blocks' scatter."""
        o = self.o
        # a move within a fraction of the probe step leaves no transient worth a block
        if self.last_target is None or abs(A - self.last_target) > 0.3 * o.probe_rel * A:
            est = yield from configure_and_settle({**self.targets(A), "frequency": self.f},
                                                  o.navg + o.transient_periods)
            self.last_target = A
            if not math.isfinite(est.frequency) or est.frequency <= 0:
                self.history.append(self._row(A, est, float("nan"), 0))
                return None, est
            e = A - self._picard(est)
            self.history.append(self._row(A, est, e, 0))
            if quick and abs(e) > 0.1 * A:
                self.evals[A] = (e, est)
                return e, est
        self.last_target = A
        vals = self.blocks.setdefault(A, [])
        limit = o.blocks_per_eval * (2 if quick else 1)
        for it in range(1, limit + 1):
            est = yield from configure_and_settle({**self.targets(A), "frequency": self.f},
                                                  o.navg)
            if not math.isfinite(est.frequency) or est.frequency <= 0:
                self.history.append(self._row(A, est, float("nan"), it))
                return None, est
            vals.append(A - self._picard(est))
            self.history.append(self._row(A, est, vals[-1], it))
            if quick and abs(np.mean(vals)) > o.sign_z * self.block_sd(est) / math.sqrt(len(vals)):
                break
        e = float(np.mean(vals))
        self.evals[A] = (e, est)
        return e, est

    def samples(self) -> list:
        """Every steady block so far at this airspeed, as (target, e)."""
        return [(A, e) for A, vals in self.blocks.items() for e in vals]

    def block_sd(self, est=None) -> float:
        """Scatter of one block's e: pooled over the targets measured at this airspeed,
        never below what the board's per-period variance implies for independent periods."""
        floor = 0.0
        if est is not None:
            var = est.fourier["response"]["var"]
            floor = math.sqrt((max(var[1], 0.0) + max(var[8], 0.0)) / self.o.navg)
        pooled = pooled_sd(self.blocks.values())
        return max(pooled or 0.0, floor)

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
    o = FlutterOptions.from_table(config.get("cbc"))
    airspeeds = list(config["parameter"]["values"])

    def plan(ctx):
        yield Configure({"kp": o.kp, "kd": o.kd, "navg": int(o.navg), "phase_mode": 1,
                         "clamp": o.clamp, "trip": o.trip, "airspeed": airspeeds[0],
                         "frequency": o.frequency_guess, **_targets(0.0, 0.0)})
        points = PointLog(ctx)
        # (airspeed, stable, target amplitude) of every cycle found so far, for warm
        # starts: a resumed campaign predicts from what the uninterrupted one would
        found = [(p["parameter"], bool(p["stable"]),
                  (p.get("extra") or {}).get("target_amplitude", p["amplitude"]))
                 for p in ctx.previous
                 if p.get("status", "ok") == "ok" and p.get("parameter") is not None]
        faults_in_a_row = 0
        for V in airspeeds:
            keys = [k for k in ctx.done if k.startswith(f"V={V:.4f}/")]
            if keys and len(keys) >= 2:
                continue                                 # this airspeed is in the file
            for attempt in range(3):
                s = _Search(V, o)
                s.found = found
                s.emit_root = _root_emitter(points, s, o)
                try:
                    yield start_segment(ctx, f"V={V:.4f}")  # from rest, its own noise
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
            if faults_in_a_row >= o.max_faults:
                yield Emit("note", {"text": f"{faults_in_a_row} faults in a row: campaign stopped"})
                break
        yield Disarm()

    return plan


def _root_emitter(points: PointLog, s, o):
    """Generator function: emit a refined root (unless the file has it already)."""
    def emit(r):
        # keyed by kind, not by order: a root missed once must not rename the others
        kind = "stable" if r["stable"] else "unstable"
        k = sum(1 for x in s.roots_emitted if x["stable"] == r["stable"])
        s.roots_emitted.append(r)
        key = f"V={s.V:.4f}/{kind}{k}"
        s.found.append((s.V, bool(r["stable"]), r["target"]))
        yield from points.emit(key, lambda index: _point_doc(index, key, s, r, o))
    return emit


def _search_airspeed(s: _Search, o: dict):
    """Generator: find, refine and emit the roots of e(A) at s.V; returns them.

    With cycles of both kinds found at earlier airspeeds, each root is first
    bracketed around its prediction (the unstable one from rest, then the stable
    one above it). Otherwise, or if a prediction misses, the scan goes upward from a
    small target amplitude, from rest, and refines each bracket as soon as it
    appears, so the target never jumps far below the orbit the rig is on (a
    phase-locked target needs the orbit to encircle its centre). The scan ends at
    the stable cycle (beyond it e only grows: the model has no further cycle there).
    """
    yield Configure({"airspeed": s.V, "frequency": s.f})
    yield from _from_rest(s, o)
    roots: list = []
    if o.warm_start:
        for stable in (False, True):
            guess = _predict(s.found, s.V, stable)
            r = None if guess is None else (yield from _warm_root(s, o, guess, stable))
            if r is None:
                break
            roots.append(r)
            yield from _emit(s, r)
        if len(roots) == 2:
            yield Disarm()
            return roots
        yield from _from_rest(s, o)
    step = o.amplitude_step
    grid = sorted(np.round(np.arange(o.amplitude_min, o.amplitude_max + 1e-12, step), 6))
    yield from _scan(s, o, grid, roots)
    yield Disarm()
    return roots


def _predict(found: list, V: float, stable: bool):
    """The amplitude of the cycle of that kind at V, extrapolated linearly from the
    two airspeeds measured last (or the last one alone); None if there is none."""
    pts = [(v, a) for v, st, a in found if st == stable and v != V]
    if not pts:
        return None
    (v1, a1) = pts[-1]
    prev = [(v, a) for v, a in pts[:-1] if v != v1]
    if not prev:
        return a1
    v0, a0 = prev[-1]
    guess = a1 + (a1 - a0) * (V - v1) / (v1 - v0)
    return min(max(guess, 0.5 * a1), 1.5 * a1)


def _warm_root(s: _Search, o: dict, guess: float, stable: bool):
    """Generator: bracket the root of that kind within +- warm_width of the guess
    (at steady state: e > 0 > e above it for an unstable cycle, the reverse for a
    stable one) and refine it; None if the bracket does not hold it."""
    w = o.warm_width
    lo = max(guess * (1 - w), o.amplitude_min)
    hi = min(guess * (1 + w), o.amplitude_max)
    e_lo, _ = yield from s.evaluate(lo, sign_only=True)
    if e_lo is None or (e_lo < 0) != stable:
        return None
    e_hi, _ = yield from s.evaluate(hi, sign_only=True)
    if e_hi is None or (e_hi > 0) != stable:
        return None
    r = yield from _refine(s, o, lo, hi)
    if r is None or not r["converged"] or r["stable"] != stable:
        return None
    return r


def _emit(s: _Search, r: dict):
    """Generator: log a refined root now (a later fault cannot lose it)."""
    if s.emit_root:
        yield from s.emit_root(r)


def _scan(s: _Search, o: dict, grid: list, roots: list):
    """Generator: evaluate e on an ascending grid, refining each sign change on the
    way; returns True once the stable cycle has been found."""
    last = None
    passed: list = []                 # grid points below `last` since the last root
    for A in grid:
        e, _ = yield from s.evaluate(A, quick=True)
        if e is None:
            last, passed = None, []
            continue
        if last is not None and last[1] * e < 0:
            # a quick evaluation can catch a transient: confirm the sign change at
            # steady state before spending a refinement on it
            lo, hi = last[0], A
            e_lo = s.evals[lo][0]
            if lo not in s.settled:
                e_lo, _ = yield from s.evaluate(lo, sign_only=True)
            if A not in s.settled:
                e, _ = yield from s.evaluate(A, sign_only=True)
            if e is not None and e_lo is not None and e_lo * e > 0 and passed:
                # the quick value at `lo` was a transient (the response still catching
                # up from below): at steady state the sign changes lower down
                lo, hi, e_lo = yield from _look_lower(s, o, passed, lo, e_lo)
                e = s.evals[hi][0]
            if e is not None and e_lo is not None and e_lo * e < 0:
                stable = e_lo < 0
                if any(lo <= x["target"] <= hi and x["stable"] == stable for x in roots):
                    if stable:
                        return True                # found by its warm start
                else:
                    r = yield from _refine(s, o, lo, hi)
                    if r is not None and r["converged"]:
                        roots.append(r)
                        yield from _emit(s, r)
                        if r["stable"]:
                            return True
                    elif r is not None:
                        yield Emit("note", {"text": f"V = {s.V}: no converged cycle in "
                                                    f"[{lo:.4f}, {hi:.4f}] m (final error "
                                                    f"{r['error']:.2e} m); not logged as a point"})
                    # back above the root, go on: at steady state, for a step up from
                    # the root can look like e > 0 for a while whatever the sign at A
                    e, _ = yield from s.evaluate(A, sign_only=True)
                passed = []
        if last is not None:
            passed.append(last[0])
        last = (A, e) if e is not None else None
    return False


def _look_lower(s: _Search, o: dict, passed: list, hi: float, e_hi: float):
    """Generator: walk down the grid points passed since the last root, each at
    steady state, to the sign change the quick scan missed; returns the bracket
    (lo, hi, e_lo), or (hi, hi, e_hi) if there is none. The rig is on a large orbit
    by now, and a phase-locked target far inside it need not hold (the orbit must
    encircle the target's centre), so each lower point is approached from rest."""
    for A in reversed(passed):
        yield from _from_rest(s, o)
        e, _ = yield from s.evaluate(A, sign_only=True)
        if e is None:
            break
        if e * e_hi < 0:
            return A, hi, e
        hi, e_hi = A, e
    return hi, hi, e_hi


def _from_rest(s: _Search, o: dict):
    """Generator: quench the aerofoil, then hand it back to the phase-locked target
    (zero for now) with the DC target reset."""
    yield from _quench(o)
    s.a0 = 0.0
    yield Configure({"phase_mode": 1, **_targets(0.0, 0.0)})
    yield Arm()


def _quench(o: dict):
    """Bring the aerofoil to rest: a zero target on the forcing phase is plain PD
    damping of the heave. Needed because the rig is bistable: without it an airspeed
    would start on the last airspeed's stable cycle."""
    yield Configure({"phase_mode": 0, **_targets(0.0, 0.0)})
    yield Arm()
    for _ in range(o.max_quench):
        est = yield Settle(periods=o.quench_periods)
        if amplitude(est.fourier["response"]["mean"]) < 0.25 * o.amplitude_min:
            break


def _refine(s: _Search, o: dict, lo: float, hi: float):
    """Inverse quadratic interpolation or regula falsi (Illinois) on e(A*) inside
    [lo, hi], falling back to bisection when two steps in a row fail to halve the
    bracket; then the root's record."""
    elo, ehi = s.evals[lo][0], s.evals[hi][0]
    if elo * ehi >= 0:
        return None
    decreasing = elo > 0 > ehi
    if o.root_method == "regression":
        return (yield from _refine_regression(s, o, lo, hi, elo, ehi, decreasing))
    b = Bracket(lo, hi, elo, ehi)
    slope = b.secant()
    slow = 0                 # steps in a row that failed to halve the bracket
    A = lo
    for _ in range(o.max_refine):
        width = b.hi - b.lo
        # interpolation closes in from one side near the root: bisect only when it
        # has stalled twice, not once
        A = 0.5 * (b.lo + b.hi) if slow >= 2 else b.next()
        e, est = yield from s.evaluate(A, coarse=True)
        if e is None:
            return None
        tol = max(o.tolerance_abs, o.tolerance_rel * A)
        b.update(A, e)
        slope = b.secant()
        # the root's location in A* is what matters: near the Hopf point e is shallow
        # (|de/dA*| << 1), so a small |e| alone can leave A* far from the root
        if abs(e) <= 0.2 * tol * abs(slope):
            break
        if (b.hi - b.lo) <= 2 * tol:
            A = b.hi - b.ehi / slope                  # the root inside the final bracket
            break
        slow = 0 if slow >= 2 or (b.hi - b.lo) <= 0.5 * width else slow + 1
    return (yield from _record_root(s, o, A, slope, decreasing))


def _record_root(s: _Search, o: dict, A: float, slope: float, decreasing: bool = True,
                 fit=None):
    """Converge fully at the root's target, then log the full-rate time series; if the
    orbit drifted (an unstable cycle held by a marginal loop), again. A regression
    root is logged once at its target: its acceptance is the root's standard error."""
    if fit is not None:
        est = yield from configure_and_settle({**s.targets(A), "frequency": s.f},
                                              o.navg + o.transient_periods, o.record_s)
        return {"target": A, "error": A - amplitude(est.fourier["response"]["mean"]),
                "estimate": est, "stable": not decreasing,
                "converged": fit.se <= o.root_se_accept * A,
                "amplitude": A, "regression": {"root_se": fit.se, "slope": fit.slope,
                                               "blocks": fit.n, "block_sd": fit.residual_sd}}
    tol = max(o.tolerance_abs, o.tolerance_rel * A)
    ok = False
    e, est = None, None
    for _ in range(3):
        e, est = yield from s.evaluate(A)
        if e is None:
            return None
        est = yield from configure_and_settle({**s.targets(A), "frequency": s.f}, o.navg,
                                              o.record_s)
        e = A - amplitude(est.fourier["response"]["mean"])
        # accepted only if the recorded orbit itself satisfies the root condition, to
        # within the tolerance on the root's location (|e| / |de/dA*|, local slope)
        ok = abs(e) <= 2 * tol * max(abs(slope), 0.05)
        if ok:
            break
    return {"target": A, "error": e, "estimate": est, "stable": not decreasing, "converged": ok}


def _refine_regression(s: _Search, o: dict, lo: float, hi: float, elo: float, ehi: float,
                       decreasing: bool):
    """Root of e inside [lo, hi] under noise, in two phases.

    1. Bracketing (Illinois) on block means while their sign is certain: it stops
       when the bracket is a few probe steps wide, or at a target whose mean e is
       inside its own scatter (the root is within the noise of it).
    2. Measure at the current root estimate, block after block; each block near it
       gives a root A - e/slope (the slope from a line through the wider
       neighbourhood, so its error enters only through the small offsets A - root);
       stop when their mean's standard error is below root_se_rel of the amplitude
       or the block budget is spent.
    Then the record at the root."""
    b = Bracket(lo, hi, elo, ehi)
    r = b.falsi()
    while b.hi - b.lo > 4 * o.probe_rel * r:
        e, est = yield from s.evaluate(r)
        if e is None:
            return None
        if abs(e) <= o.sign_z * s.block_sd(est) / math.sqrt(len(s.blocks[r])):
            break                                # within the noise of the root
        b.update(r, e)
        r = b.falsi()
    lo, hi = b.lo, b.hi
    slope = secant = b.secant()
    used, fit = 0, None
    while True:
        fit = root_from_blocks(s.samples(), r, o.probe_rel * r, slope, s.block_sd(),
                               min_slope=0.25 * abs(secant))
        if fit is not None:
            # the bracket's ends had a sign outside the noise, the root is between
            # them; a root close to an end may lie just beyond it (that end's sign was
            # the noise's after all), so allow a couple of probe steps
            d = 2 * o.probe_rel * fit.root
            slope, r = fit.slope, min(max(fit.root, lo - d), hi + d)
            if fit.se <= o.root_se_rel * r and fit.n >= 2 * o.blocks_per_eval:
                break
        if used >= o.max_blocks:
            break
        n0 = len(s.samples())
        e, _ = yield from s.evaluate(r)
        if e is None:
            return None
        used += len(s.samples()) - n0
    if fit is None or (fit.slope < 0) != decreasing:
        return None
    return (yield from _record_root(s, o, r, fit.slope, decreasing, fit=fit))


def _point_doc(index, key, s: _Search, r: dict, o: FlutterOptions) -> dict:
    est = r["estimate"]
    resp = est.fourier["response"]["mean"]
    extra = {"target_amplitude": r["target"], "final_error": r["error"],
             "dc": float(resp[0]), "evaluations": len(s.history),
             "root_method": o.root_method}
    if "regression" in r:
        # the amplitude logged is the regression's fixed point; the record's own too
        reg = r["regression"]
        extra.update({"root_se": reg["root_se"], "root_slope": reg["slope"],
                      "root_blocks": reg["blocks"], "block_sd": reg["block_sd"],
                      "record_amplitude": amplitude(resp)})
    settings = {"kp": o.kp, "kd": o.kd, "airspeed": s.V, "frequency": s.f,
                "navg": o.navg, **s.targets(r["target"])}
    return point_doc(
        index=index, key=key, rig="flutter", parameter=s.V, parameter_name="airspeed",
        frequency=est.frequency, amplitude=r.get("amplitude", amplitude(resp)),
        stable=r["stable"], stability_method=STABILITY_METHOD, converged=r["converged"],
        settings=settings, estimate=est, dc=resp[0], history=s.history,
        wall_time=time.time() - s.t_wall, extra=extra)
