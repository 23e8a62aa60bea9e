"""The holding control as a known input (the aerofoil): a point held with some control is
an orbit of the *controlled* system, so a fit that knows the recorded control force fits
it as one, instead of misreading it as an open-loop orbit.

The control acts on heave (the rig's actuator); its record is in the channel's own unit
(N on a simulated campaign, volts in the lee2020 files), so the force is ``gain`` times
it. The gain is 1 where the control is recorded as a force, the user's where given, and
otherwise identified with the mechanistic parameters by the same equation-error least
squares (a column of the heave equation). Only the training sees the input: the fitted
model's diagram is the open-loop system's (no input), the diagram the data stands for.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from .._systems import system_kind
from ..data.orbit import DataError, OrbitDataset
from .identify import TrainingData

FORCE_UNIT = "N"        # a control recorded in this unit is the force itself (gain 1)


@dataclass(frozen=True)
class ControlChoice:
    """The user's choice to take the recorded holding control as a known input (``ude-fit
    fit``, ``loop``, ``refine`` and ``pipeline`` with ``--control-input``): the system, and
    the gain in N per unit of the record where the user gives it (None: 1 for a record in
    N, else identified from the data)."""
    system: str
    gain: float | None = None

    def __post_init__(self):
        if not system_kind(self.system).autonomous:
            raise ValueError("--control-input applies to --system flutter only (the "
                             "oscillator's excitation already includes its control)")
        g = self.gain
        if g is not None and not (isinstance(g, (int, float)) and not isinstance(g, bool)
                                  and math.isfinite(g) and g != 0):
            raise ValueError(f"--control-gain must be a finite number other than 0, "
                             f"not {g!r}")

    @classmethod
    def of(cls, system: str, control_input: bool, gain: float | None
           ) -> "ControlChoice | None":
        """The choice the flags make (None without --control-input); ValueError naming
        the flag for a gain without --control-input or a bad one."""
        if gain is not None and not control_input:
            raise ValueError("--control-gain needs --control-input")
        return cls(system, gain) if control_input else None


@dataclass(frozen=True)
class ControlInput:
    """How a fit takes the recorded control: its unit, the gain (N per unit; None until
    identified) and where the gain came from."""
    unit: str
    gain: float | None
    source: str

    def to_json(self) -> dict:
        return {"unit": self.unit, "gain": self.gain, "gain_source": self.source}


def control_input(ds: OrbitDataset, given_gain: float | None) -> ControlInput:
    """The dataset's control input: every orbit must carry its control record in one unit
    (a DataError naming the first that does not)."""
    units = set()
    for o in ds:
        if o.control is None or o.holding is None:
            raise DataError(f"{o.source}: no recorded control, so --control-input cannot "
                            "use it (leave the option out)")
        units.add(o.holding.control_unit)
    if len(units) != 1:
        raise DataError(f"the points' controls are recorded in different units "
                        f"({', '.join(sorted(units))}); --control-input needs one")
    unit = units.pop()
    if given_gain is not None:
        return ControlInput(unit, float(given_gain), "given (--control-gain)")
    if unit == FORCE_UNIT:
        return ControlInput(unit, 1.0, "the control is recorded as a force (N)")
    return ControlInput(unit, None, "identified with the mechanistic parameters "
                                    "(equation error, heave equation)")


def with_control(data: TrainingData, ds: OrbitDataset, gain: float) -> TrainingData:
    """``data`` with every orbit's imposed heave force: ``gain`` times its recorded
    control, in the orbit's phase frame (the drive's omega is the orbit's own)."""
    if not math.isfinite(gain):
        raise ValueError(f"the control gain must be finite, not {gain!r}")
    fc = jnp.asarray(np.stack([gain * np.asarray(o.control, float) for o in ds]))
    return eqx.tree_at(lambda d: d.drive.fc, data, fc)


def against_heave_stiffness(ds: OrbitDataset, gain: float, k_heave: float
                            ) -> list[float | None]:
    """Per point, how much of the heave spring's force the holding control supplied: the
    control force's fundamental against the spring's at the orbit's heave fundamental,
    |gain u1| / (k_h |h1|), with the gain in N per unit of the record and k_h the
    mechanistic model's heave stiffness. A non-invasive point gives 0; None where the point
    has no control record or the ratio has no meaning (k_h or the amplitude 0)."""
    out = []
    for o in ds:
        spring = k_heave * o.amplitude
        if o.holding is None or not spring > 0:
            out.append(None)
        else:
            out.append(abs(gain) * o.holding.control_amplitude / spring)
    return out
