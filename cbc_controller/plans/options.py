"""The options of each plan: one frozen dataclass per plan, checking itself when built.

A campaign's ``[cbc]`` table becomes one of these when the campaign file is read
(`campaign.validate`), so a bad field is a one-line error at ``cbc-campaign validate``,
never a surprise in the middle of a campaign. Every field's type is checked (an integer
is accepted for a float field and stored as a float), integers are never negative,
string fields with a fixed set of values say which, and the fields that are rig
settings are checked against the register map's ranges for that rig.
"""

from __future__ import annotations

import math
import typing
from dataclasses import asdict, dataclass, fields
from typing import ClassVar

from rig_sim.device import register_map as M

ROOT_METHODS = ("regula_falsi", "regression")


@dataclass(frozen=True)
class PlanOptions:
    """Base: type, sign, choice and register-range checks over the dataclass's fields."""

    RIG: ClassVar[str] = ""
    # fields that are rig settings: field -> register (its range for RIG applies)
    REGISTERS: ClassVar[dict[str, str]] = {}
    # fields with a fixed set of values
    CHOICES: ClassVar[dict[str, tuple[str, ...]]] = {}

    def __post_init__(self) -> None:
        hints = typing.get_type_hints(type(self))
        for f in fields(self):
            value = typed(f"cbc.{f.name}", getattr(self, f.name), hints[f.name])
            if hints[f.name] is int and value < 0:
                raise ValueError(f"cbc.{f.name} = {value}: must be >= 0")
            object.__setattr__(self, f.name, value)
            choices = self.CHOICES.get(f.name)
            if choices and value not in choices:
                raise ValueError(f"cbc.{f.name} = {value!r}: must be one of "
                                 + ", ".join(f'"{c}"' for c in choices))
            register = self.REGISTERS.get(f.name)
            if register is not None:
                reg = M.BY_NAME[register]
                lo, hi = reg.range_for(self.RIG)
                if not lo <= value <= hi:
                    raise ValueError(f"cbc.{f.name} = {value:g}: outside {lo:g}..{hi:g} "
                                     f"{reg.unit} ({register})")

    @classmethod
    def from_table(cls, table: dict | None):
        """The options from a campaign's ``[cbc]`` table (missing fields take their defaults)."""
        table = dict(table or {})
        known = [f.name for f in fields(cls)]
        for k in table:
            if k not in known:
                raise ValueError(f"cbc.{k}: unknown field for the {cls.RIG} plan "
                                 f"(known: {', '.join(sorted(known))})")
        return cls(**table)

    def as_dict(self) -> dict:
        return asdict(self)


def typed(field: str, value, kind):
    """The value of a field of type `kind` (float, int, bool or str), or ValueError naming the
    field (a number given as an integer becomes a float)."""
    if kind is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ValueError(f"{field} = {value!r}: expected a number")
        if not math.isfinite(value):
            raise ValueError(f"{field} = {value!r}: not a finite number")
        return float(value)
    if kind is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ValueError(f"{field} = {value!r}: expected an integer")
        return value
    if not isinstance(value, kind):
        raise ValueError(f"{field} = {value!r}: expected {kind.__name__}")
    return value


@dataclass(frozen=True)
class FlutterOptions(PlanOptions):
    """The aerofoil plan (plans.autonomous): bracketing search on the target amplitude."""

    RIG: ClassVar[str] = "flutter"
    REGISTERS: ClassVar[dict[str, str]] = {"kp": "kp", "kd": "kd", "navg": "navg",
                                           "clamp": "clamp", "trip": "trip",
                                           "frequency_guess": "frequency"}
    CHOICES: ClassVar[dict[str, tuple[str, ...]]] = {"root_method": ROOT_METHODS}

    kp: float = 200.0                 # N/m
    kd: float = 60.0                  # N s/m
    navg: int = 4                     # periods in the board's running mean/variance
    transient_periods: int = 1
    frequency_guess: float = 2.4      # Hz, the phase lock's first frequency
    amplitude_min: float = 0.006      # m, the scan's grid
    amplitude_max: float = 0.14
    amplitude_step: float = 0.012
    tolerance_abs: float = 2e-5
    tolerance_rel: float = 1e-3
    frequency_tolerance: float = 0.002
    dc_tolerance: float = 5e-5
    max_picard: int = 8
    max_refine: int = 16
    variance_rel: float = 5e-3
    max_gate_polls: int = 4
    record_s: float = 2.0
    clamp: float = 300.0
    trip: float = 0.2
    picard_harmonics: bool = False
    max_faults: int = 3
    quench_periods: int = 6
    max_quench: int = 8
    # bracket each root around its prediction from the airspeeds before (+- warm_width
    # of it) before falling back to the scan from a small amplitude
    warm_start: bool = True
    warm_width: float = 0.08
    # under process noise: "regression" (see plans.autonomous)
    root_method: str = "regula_falsi"
    blocks_per_eval: int = 3
    sign_z: float = 3.0
    root_se_rel: float = 0.003
    root_se_accept: float = 0.02
    max_blocks: int = 48
    probe_rel: float = 0.025


@dataclass(frozen=True)
class ForcedOptions(PlanOptions):
    """The oscillator plan (plans.forced): S-curves by sweeping the target's fundamental."""

    RIG: ClassVar[str] = "oscillator"
    REGISTERS: ClassVar[dict[str, str]] = {"kp": "kp", "kd": "kd", "navg": "navg",
                                           "clamp": "clamp", "trip": "trip"}

    # controller (board settings)
    kp: float = 1.0e4                 # proportional gain, (m/s^2)/m
    kd: float = 50.0                  # derivative gain, (m/s^2)/(m/s)
    filter_hz: float = 0.0            # error low-pass on the board, 0 = off
    navg: int = 8                     # periods in the board's running mean/variance
    transient_periods: int = 3        # periods dropped after a new target
    clamp: float = 100.0              # output clamp, m/s^2 (the shaker's limit)
    trip: float = 0.016               # amplitude trip on |x|, m
    forcing_amplitude: float = 0.0    # host forcing, m/s^2 (0: the controller provides all)
    # amplitude sweep (m)
    amplitude_start: float = 3.0e-4
    amplitude_step: float = 3.0e-4    # first step
    step_min: float = 4.0e-5
    step_max: float = 6.0e-4
    turn_max_deg: float = 20.0
    descent_frac: float = 0.4
    amplitude_stop: float = 0.0       # > 0: end every sweep here instead of past the folds
    amplitude_max: float = 0.012      # largest response amplitude (m)
    beyond_fold: float = 0.2          # go on to (1 + beyond_fold) x the jump-down fold
    phi_max: float = 80.0             # end a sweep once the sustaining forcing exceeds this
    fold_margin: float = 0.02
    probe_min: float = 5.0e-6         # smallest probe offset, m
    fold_refine: int = 3              # points bisecting towards a fold once it is passed
    fold_gap: float = 0.01            # ... until its neighbours are this close (relative)
    # convergence
    max_picard: int = 8
    picard_from_control: bool = True
    noninvasive_tol: float = 0.005
    noninvasive_sigmas: float = 2.0
    variance_rel: float = 0.004
    max_gate_polls: int = 4
    record_s: float = 0.25
    # faults
    max_fault_retries: int = 2
    max_fault_skips: int = 3
    max_restarts: int = 3
    rearm_ramp: int = 5               # re-arm onto the last good target in this many steps
    rearm_tries: int = 10
    rearm_fraction: float = 0.8       # ... onto this fraction of it (the last good point
                                      # may be just under the trip level)


OPTIONS = {"flutter": FlutterOptions, "oscillator": ForcedOptions}


def plan_options(config: dict) -> PlanOptions:
    """The typed options of a campaign config's plan (ValueError naming the field)."""
    return OPTIONS[config["campaign"]["rig"]].from_table(config.get("cbc"))
