"""How invasive the control that held a measured orbit was, from the point's own record.

Control-based continuation holds an orbit with a feedback controller whose target is
adjusted until the control's fundamental vanishes; then the orbit is one of the open-loop
system. A point is as good as that holds, so every point gets:

* the control signal's first-harmonic amplitude (in the channel's own unit: N on a
  simulated aerofoil campaign, m/s^2 on the oscillator, volts in the lee2020 files, whose
  actuator gain is unknown), with its standard error from the same channel's noise (the
  residual RMS after the K-harmonic fit, sigma, gives sigma sqrt(2 / N) for one
  harmonic's amplitude over N samples, for noise white over the record);
* where the controller's gains are known (campaign files record kp and kd), that
  amplitude against the response's fundamental scaled by the gains, |u1| / (|kp + i w kd|
  |x1|): the control force relative to the force the same controller would apply with a
  zero target;
* the target against the response: |T1 - X1| / |X1| of the complex first harmonics.

The rule for calling a point *invasive* is general, not a threshold from any dataset: its
control fundamental is distinguishable from the channel's noise, more than
:data:`SIGNIFICANCE` standard errors from zero.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .._fourier import K, _fit

SIGNIFICANCE = 3.0      # standard errors: the usual "distinguishable from noise"


def _fundamental(c) -> complex:
    return complex(c[1], -c[1 + K])


@dataclass(frozen=True)
class Holding:
    """Figures of one point's holding control (see the module's docstring)."""
    control_amplitude: float
    control_standard_error: float
    control_unit: str
    target_mismatch: float | None
    control_relative_to_gains: float | None = None

    @property
    def significance(self) -> float:
        """The control fundamental in standard errors of the channel's noise."""
        if self.control_standard_error > 0:
            return self.control_amplitude / self.control_standard_error
        return math.inf if self.control_amplitude > 0 else 0.0

    @property
    def invasive(self) -> bool:
        return self.significance > SIGNIFICANCE

    def to_json(self) -> dict:
        return {"control_amplitude": self.control_amplitude,
                "control_standard_error": self.control_standard_error,
                "control_unit": self.control_unit,
                "control_significance": self.significance,
                "control_relative_to_gains": self.control_relative_to_gains,
                "target_mismatch": self.target_mismatch,
                "invasive": self.invasive}


def measure_holding(phi, response, target, control, unit: str, *, valid=None,
                    gains: tuple[float, float] | None = None,
                    omega: float | None = None) -> Holding | None:
    """The :class:`Holding` of a record sampled at phases ``phi`` (the orbit's own
    frequency, rad): ``response`` and ``target`` in one unit, ``control`` in ``unit``;
    ``valid`` (N,) marks the usable samples (all by default); ``gains`` (kp, kd) with
    ``omega`` (rad/s) where the controller's gains are known. None where the record has no
    finite control samples."""
    phi = np.asarray(phi, float)
    Y = np.column_stack([np.asarray(response, float), np.asarray(target, float),
                         np.asarray(control, float)])
    ok = np.isfinite(Y) & (np.ones_like(Y, bool) if valid is None
                           else np.asarray(valid, bool)[:, None])
    n = ok.sum(axis=0)
    if n[2] < 2 * (2 * K + 1):
        return None
    coef, rms = _fit(phi, np.where(ok, Y, 0.0), K, ok)
    x1, t1, u1 = (_fundamental(c) for c in coef)
    amp = abs(u1)
    se = float(rms[2] * math.sqrt(2.0 / n[2]))
    mismatch = abs(t1 - x1) / abs(x1) if abs(x1) > 0 and n[1] >= 2 * (2 * K + 1) else None
    rel = None
    if gains is not None and omega is not None and all(map(math.isfinite, gains)):
        scale = abs(complex(gains[0], omega * gains[1])) * abs(x1)
        rel = amp / scale if scale > 0 else None
    return Holding(float(amp), se, unit, None if mismatch is None else float(mismatch), rel)
