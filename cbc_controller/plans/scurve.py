"""The state of one S-curve sweep of the forced plan: the (A, Phi) history, step control and
fold bookkeeping (see plans.forced for the method)."""

from __future__ import annotations

import math

import numpy as np

from ..harmonics import NH
from .forced_numbers import parabola, slope_at_last
from .options import ForcedOptions

TARGET_MAX = 0.0195   # target coefficients are limited to +-0.02 m by the register map


class Sweep:
    """The S-curve at one frequency: history, step control, fold bookkeeping."""

    def __init__(self, f: float, o: ForcedOptions, sample_rate: float):
        self.f = float(f)
        self.o = o
        self.sample_rate = sample_rate                       # the board's, Hz (its PD law)
        self.pts: list[tuple[float, float]] = [(0.0, 0.0)]   # (A, Phi), the origin first
        self.sig: list[float] = [0.0]
        self.labels: list[bool] = []
        self.targets_done: list[float] = []
        self.harm: list[tuple[float, np.ndarray]] = []       # (target, converged 15-vector)
        self.h = o.amplitude_step
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
        c2 = float(parabola(self.pts[-3:])[0]) if len(self.pts) >= 3 else 0.0
        return slope, se, c2

    def update_folds(self):
        """Confirm folds with hysteresis; returns a new fold's record or None."""
        if self.phase >= 2 or len(self.pts) < 3:
            return None
        i = len(self.pts) - 1
        phi_i = self.pts[i][1]
        ext = self.pts[self.ext_i][1]
        margin = (self.o.fold_margin * max(ext, 1e-12)
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
        if len(self.pts) > 1 and phi_next > o.phi_max:
            return f"forcing would exceed phi_max ({phi_next:.1f} m/s^2 predicted)"
        if o.amplitude_stop > 0:
            if A_next > o.amplitude_stop + 1e-9:
                return "amplitude_stop reached"
        elif self.phase >= 2:
            # in measured amplitude (the target differs from it by |forcing / C(w)|)
            if self.pts[-1][0] >= (1 + o.beyond_fold) * self.folds[1]["amplitude"]:
                return "past both folds"
        # amplitude_max bounds the response; the target runs ahead of it by
        # |forcing / C(w)| (millimetres on the upper branch), so predict the response
        A_meas = self.pts[-1][0]
        if len(self.pts) >= 3 and self.targets_done[-1] > self.targets_done[-2]:
            dT = self.targets_done[-1] - self.targets_done[-2]
            gain = (self.pts[-1][0] - self.pts[-2][0]) / dT
            A_meas += max(gain, 0.0) * (A_next - self.targets_done[-1])
        if A_meas > o.amplitude_max + 1e-9:
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
                if ang > o.turn_max_deg:
                    h *= 0.5
                elif ang < o.turn_max_deg / 3:
                    h *= 1.5
        h = min(max(h, o.step_min), o.step_max)
        if len(self.pts) >= 3 and self.phase < 2:
            (A1, P1), (A2, P2) = self.pts[-2:]
            # target and measured amplitude differ: scale the guards to target units
            ratio = (self.targets_done[-1] / A2) if A2 > 0 else 1.0
            sec = (P2 - P1) / (A2 - A1) if A2 != A1 else 0.0
            if sec < 0:                                 # falling: Phi must turn before 0
                h = min(h, max(o.step_min, o.descent_frac * P2 / -sec * ratio))
            if len(self.pts) >= 4:
                c2, c1, _ = parabola(self.pts[-3:])
                if c2 != 0:
                    Av = -c1 / (2 * c2)
                    if A2 < Av < A2 + h / ratio:        # a fold ahead within the step
                        h = max(o.step_min, 0.5 * (Av - A2) * ratio)
        self.h = h
        return h
