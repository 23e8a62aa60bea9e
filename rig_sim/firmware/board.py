"""The embedded controller ("firmware") of a virtual rig, as a Python object.

`Board` owns the physics state and everything a real CBC board keeps in its
memory: settings, the control law's state, the Fourier estimator, the sample
ring buffer, safety latches and counters. It knows nothing about Modbus; the
device layer maps registers onto its settings and readings.

Threading: `advance` may run in a pacing thread while the protocol thread reads;
every public method takes `self.lock`.
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass, field
from types import MappingProxyType

import numpy as np

from ..physics.configuration import configured_params
from ..physics.effects import EFFECT_SLOTS, check_plugin, load_plugin, parse_effects
from ..physics.flutter import flutter_kernel_params
from ..physics.oscillator import oscillator_kernel_params
from ..device.register_map import BY_NAME
from . import layout as L
from .kernel import advance as _advance


class SettingError(ValueError):
    """A setting outside its documented range (answered as ILLEGAL DATA VALUE)."""


class StateError(RuntimeError):
    """A command the board refuses in its present state (e.g. arm while faulted)."""


@dataclass(frozen=True)
class RigSpec:
    """Fixed properties of one rig model: its datasheet numbers."""
    kind: str
    model: str
    rate_hz: float
    n_state: int
    ndof: int
    saturation: float          # actuator saturation (N for flutter, m/s^2 for the shaker)
    sensor_noise: tuple        # sd of x, x', q2, q2'
    full_scale: tuple          # ADC full scale of x, x', q2, q2'
    param_full_scale: float
    default_trip: float
    default_freq: float
    default_param: float


FLUTTER_SPEC = RigSpec(
    kind="flutter", model="VCL-FLUTTER-2DOF", rate_hz=5000.0, n_state=6, ndof=2,
    saturation=300.0,
    sensor_noise=(5e-5, 2e-3, 2e-4, 5e-3),
    full_scale=(0.25, 2.5, 0.5, 10.0),
    param_full_scale=50.0, default_trip=0.2, default_freq=2.4, default_param=0.0,
)

OSCILLATOR_SPEC = RigSpec(
    kind="oscillator", model="VCL-EDOSC-1DOF", rate_hz=10000.0, n_state=3, ndof=1,
    saturation=100.0,
    sensor_noise=(2e-6, 2e-3, 0.0, 0.0),
    full_scale=(0.02, 3.0, 1.0, 1.0),
    param_full_scale=100.0, default_trip=0.018, default_freq=23.0, default_param=0.0,
)

SPECS = {"flutter": FLUTTER_SPEC, "oscillator": OSCILLATOR_SPEC}


@dataclass
class RigOptions:
    """Start-up options (the CLI's serve flags)."""
    kind: str = "flutter"
    sigma: float = 0.0                 # process-noise intensity
    seed: int = 0
    effects: list = field(default_factory=list)   # ["NAME=VALUE", ...]
    physics: list = field(default_factory=list)   # ["NAME=VALUE", ...] off the design values
    plugin: str | None = None
    sensor_noise: bool = True
    adc_bits: int = 16
    latency_samples: int = 0
    rate_hz: float | None = None       # None: the rig's default


class Board:
    def __init__(self, options: RigOptions):
        if options.kind not in SPECS:
            raise SettingError(f"unknown rig {options.kind!r} (flutter or oscillator)")
        self.options = options
        self.spec = spec = SPECS[options.kind]
        self.lock = threading.RLock()
        self.params = configured_params(spec.kind, options.physics)
        self.effect_vector, self.effects = parse_effects(spec.kind, options.effects)
        self.plugin = None
        if options.plugin:
            self.plugin = load_plugin(options.plugin)
            check_plugin(self.plugin, spec.ndof, self._plugin_params())
        rate = options.rate_hz or spec.rate_hz
        if not (500.0 <= rate <= 50000.0):
            raise SettingError(f"rate {rate} Hz outside 500..50000 Hz")
        if not (8 <= options.adc_bits <= 24):
            raise SettingError(f"adc bits {options.adc_bits} outside 8..24")
        if not (0 <= options.latency_samples < L.DELAY_MAX):
            raise SettingError(f"latency {options.latency_samples} samples outside 0..{L.DELAY_MAX - 1}")
        if not (options.sigma >= 0.0 and math.isfinite(options.sigma)):
            raise SettingError(f"noise sigma {options.sigma} must be finite and >= 0")
        self.rate = rate
        self.dt = 1.0 / rate
        self.rng = np.random.Generator(np.random.PCG64(options.seed))
        self.noise_seed = options.seed % 2**31         # reads back the last seed written

        rig = np.zeros(L.RIG_SIZE)
        rig[L.RIG_KIND] = 0.0 if spec.kind == "flutter" else 1.0
        rig[L.RIG_DT] = self.dt
        rig[L.RIG_SAT] = spec.saturation
        rig[L.RIG_SIGMA] = options.sigma
        for j in range(4):
            rig[L.RIG_NOISE + j] = spec.sensor_noise[j] if options.sensor_noise else 0.0
            rig[L.RIG_FS + j] = spec.full_scale[j]
            rig[L.RIG_LSB + j] = 2.0 * spec.full_scale[j] / 2 ** options.adc_bits
        rig[L.RIG_MASS] = getattr(self.params, "mass", 1.0)
        rig[L.RIG_LATENCY] = options.latency_samples
        rig[L.RIG_U_FS] = spec.saturation
        rig[L.RIG_PARAM_FS] = spec.param_full_scale
        self.rig = rig

        self.cfg = np.zeros(L.CFG_SIZE)
        self.cfg[L.CFG_FREQ] = spec.default_freq
        self.cfg[L.CFG_PARAM] = spec.default_param
        self.cfg[L.CFG_CLAMP] = spec.saturation
        self.cfg[L.CFG_TRIP] = spec.default_trip
        self.cfg[L.CFG_NAVG] = 10
        self.cfg[L.CFG_RING_DEC] = 1
        self.cfg[L.CFG_PHASE_MODE] = 1.0 if spec.kind == "flutter" else 0.0
        self.watchdog_s = 1.0

        self.y = np.zeros(spec.n_state)
        self.fw = np.zeros(L.FW_SIZE)
        self.ic = np.zeros(L.IC_SIZE, dtype=np.int64)
        self.acc = np.zeros((L.NCH, L.NCOEF))
        self.hist = np.zeros((L.NCH, L.HIST_MAX, L.NCOEF))
        self.fhist = np.zeros(L.HIST_MAX)
        self.fmean = np.zeros(1)
        self.fvar = np.zeros(1)
        self.cmean = np.zeros((L.NCH, L.NCOEF))
        self.cvar = np.zeros((L.NCH, L.NCOEF))
        self.delay = np.zeros(L.DELAY_MAX)
        self.ring = np.zeros((L.RING_CAP, L.REC_SIZE), dtype=np.uint16)
        self.ext = np.zeros(2)
        self.overruns = 0
        self.watchdog_trips = 0
        self.sim_time_at_heartbeat = 0.0
        self.wall_at_heartbeat = time.monotonic()
        self._update_physics()

    # ------------------------------------------------------------------ physics
    def _plugin_params(self) -> MappingProxyType:
        d = dict(self.params.as_dict())
        if self.spec.kind == "flutter":
            d["airspeed"] = float(self.cfg[L.CFG_PARAM]) if hasattr(self, "cfg") else 0.0
        else:
            d["forcing_amplitude"] = float(self.cfg[L.CFG_PARAM]) if hasattr(self, "cfg") else 0.0
            d["forcing_frequency"] = float(self.cfg[L.CFG_FREQ]) if hasattr(self, "cfg") else 0.0
        return MappingProxyType(d)

    def _update_physics(self) -> None:
        if self.spec.kind == "flutter":
            self.phys = flutter_kernel_params(self.params, float(self.cfg[L.CFG_PARAM]))
        else:
            self.phys = oscillator_kernel_params(self.params)
        self._plugin_view = self._plugin_params() if self.plugin else None

    @property
    def seq(self) -> int:
        return int(self.ic[L.IC_SEQ])

    @property
    def sim_time(self) -> float:
        return self.seq * self.dt

    def advance(self, nsteps: int) -> int:
        """Run the board nsteps samples; returns estimator periods completed."""
        if nsteps <= 0:
            return 0
        with self.lock:
            noise = self.rng.standard_normal((nsteps, 5))
            if self.plugin is None:
                return _advance(nsteps, self.y, self.fw, self.ic, self.cfg, self.rig,
                                self.phys, self.effect_vector, noise, self.ext, self.acc,
                                self.hist, self.fhist, self.fmean, self.fvar, self.cmean,
                                self.cvar, self.delay, self.ring)
            done = 0
            ndof = self.spec.ndof
            for s in range(nsteps):
                q, qd = self._dof_state()
                f = np.asarray(self.plugin(self.sim_time, q, qd, self._plugin_view), dtype=float)
                if f.shape != (ndof,) or not np.all(np.isfinite(f)):
                    f = np.zeros(ndof)  # a broken plugin must not crash the rig mid-run
                self.ext[:ndof] = f
                done += _advance(1, self.y, self.fw, self.ic, self.cfg, self.rig, self.phys,
                                 self.effect_vector, noise[s:s + 1], self.ext, self.acc,
                                 self.hist, self.fhist, self.fmean, self.fvar, self.cmean,
                                 self.cvar, self.delay, self.ring)
            return done

    def _dof_state(self):
        if self.spec.kind == "flutter":
            return self.y[0:2].copy(), self.y[3:5].copy()
        return self.y[0:1].copy(), self.y[1:2].copy()

    # ------------------------------------------------------------------ settings
    def set(self, name: str, value: float) -> None:
        """Validate and apply one setting; raise SettingError naming the problem."""
        if not math.isfinite(value):
            raise SettingError(f"{name}: not a finite number")
        with self.lock:
            setter = getattr(self, f"_set_{name}", None)
            if setter is not None:
                setter(value)
                return
            if name.startswith("target_"):
                idx = _TARGET_INDEX.get(name)
                if idx is None:
                    raise SettingError(f"unknown setting {name}")
                _check(name, value, *map_range(self.spec.kind, name))
                self.cfg[L.CFG_TARGET + idx] = value
                return
            raise SettingError(f"unknown setting {name}")

    def get(self, name: str) -> float:
        with self.lock:
            if name in _CFG_NAMES:
                return float(self.cfg[_CFG_NAMES[name]])
            if name.startswith("target_") and name in _TARGET_INDEX:
                return float(self.cfg[L.CFG_TARGET + _TARGET_INDEX[name]])
            if name == "watchdog_timeout":
                return self.watchdog_s
            if name == "noise_seed":
                return float(self.noise_seed)
            raise SettingError(f"unknown setting {name}")

    def _set_kp(self, v):
        _check("kp", v, *map_range(self.spec.kind, "kp"))
        self.cfg[L.CFG_KP] = v

    def _set_kd(self, v):
        _check("kd", v, *map_range(self.spec.kind, "kd"))
        self.cfg[L.CFG_KD] = v

    def _set_phase_mode(self, v):
        if v not in (0.0, 1.0):
            raise SettingError("phase_mode: must be 0 (forcing) or 1 (phase-locked)")
        if self.cfg[L.CFG_PHASE_MODE] != v:
            self.cfg[L.CFG_PHASE_MODE] = v
            self._reset_estimator()

    def _set_frequency(self, v):
        _check("frequency", v, *map_range(self.spec.kind, "frequency"))
        self.cfg[L.CFG_FREQ] = v

    def _set_parameter(self, v):
        _check("parameter", v, *map_range(self.spec.kind, "parameter"))
        self.cfg[L.CFG_PARAM] = v
        self._update_physics()

    def _set_clamp(self, v):
        _check("clamp", v, *map_range(self.spec.kind, "clamp"))
        self.cfg[L.CFG_CLAMP] = v

    def _set_trip(self, v):
        _check("trip", v, *map_range(self.spec.kind, "trip"))
        self.cfg[L.CFG_TRIP] = v

    def _set_navg(self, v):
        if v != int(v):
            raise SettingError("navg: must be an integer")
        _check("navg", v, *map_range(self.spec.kind, "navg"))
        self.cfg[L.CFG_NAVG] = v

    def _set_filter_hz(self, v):
        _check("filter_hz", v, *map_range(self.spec.kind, "filter_hz"))
        self.cfg[L.CFG_FILTER_HZ] = v

    def _set_ring_decimation(self, v):
        if v != int(v):
            raise SettingError("ring_decimation: must be an integer")
        _check("ring_decimation", v, *map_range(self.spec.kind, "ring_decimation"))
        self.cfg[L.CFG_RING_DEC] = v

    def _set_watchdog_timeout(self, v):
        _check("watchdog_timeout", v, *map_range(self.spec.kind, "watchdog_timeout"))
        self.watchdog_s = v

    def _set_noise_seed(self, v):
        """A reproducible restart (lockstep): the structure at rest, the firmware's state and
        estimator cleared, disarmed, the noise streams seeded from `v`: from here on the run
        is the same as a fresh board's given the same settings and host commands, whatever
        happened before. Settings, the latched fault and the counters (samples, periods,
        ring) stay, so a host keeps its bearings."""
        if v != int(v):
            raise SettingError("noise_seed: must be an integer")
        _check("noise_seed", v, *map_range(self.spec.kind, "noise_seed"))
        self.noise_seed = int(v)
        self.rng = np.random.Generator(np.random.PCG64(self.noise_seed))
        self.y[:] = 0.0
        self.fw[:] = 0.0
        self.delay[:] = 0.0
        self.ext[:] = 0.0
        self.ic[L.IC_DELAY_POS] = 0
        self.ic[L.IC_ARMED] = 0
        self._reset_estimator()

    # ------------------------------------------------------------------ commands
    def arm(self) -> None:
        with self.lock:
            if self.ic[L.IC_FAULT] != L.FAULT_NONE:
                raise StateError("cannot arm while a fault is latched; reset the fault first")
            self.ic[L.IC_ARMED] = 1
            self.heartbeat()

    def disarm(self) -> None:
        with self.lock:
            self.ic[L.IC_ARMED] = 0

    def reset_fault(self) -> None:
        with self.lock:
            self.ic[L.IC_FAULT] = L.FAULT_NONE

    def _reset_estimator(self) -> None:
        self.acc[:] = 0.0
        self.hist[:] = 0.0
        self.fhist[:] = 0.0
        self.cmean[:] = 0.0
        self.cvar[:] = 0.0
        self.fmean[:] = 0.0
        self.fvar[:] = 0.0
        self.ic[L.IC_HIST_N] = 0
        self.ic[L.IC_HIST_POS] = 0
        self.fw[L.FW_TH_UNWRAP] = 0.0
        self.fw[L.FW_PERIOD_T] = 0.0

    def reset_averages(self) -> None:
        with self.lock:
            self._reset_estimator()

    def heartbeat(self) -> None:
        with self.lock:
            self.wall_at_heartbeat = time.monotonic()
            self.sim_time_at_heartbeat = self.sim_time

    def check_watchdog(self, lockstep: bool) -> bool:
        """Trip the watchdog if the host has been silent too long. True if it fired."""
        with self.lock:
            silent = (self.sim_time - self.sim_time_at_heartbeat if lockstep
                      else time.monotonic() - self.wall_at_heartbeat)
            if silent <= self.watchdog_s:
                return False
            if self.ic[L.IC_ARMED]:
                self.ic[L.IC_ARMED] = 0
                if self.ic[L.IC_FAULT] == L.FAULT_NONE:
                    self.ic[L.IC_FAULT] = L.FAULT_WATCHDOG
                self.watchdog_trips += 1
            return True

    # ------------------------------------------------------------------ readings
    @property
    def armed(self) -> bool:
        return bool(self.ic[L.IC_ARMED])

    @property
    def fault(self) -> int:
        return int(self.ic[L.IC_FAULT])

    def true_state(self) -> np.ndarray:
        """The hidden physical state (for tests and the truth model only)."""
        with self.lock:
            return self.y.copy()

    def set_true_state(self, y) -> None:
        """Place the hidden state (tests only: e.g. start on a known orbit)."""
        with self.lock:
            self.y[:] = y


_CFG_NAMES = {
    "kp": L.CFG_KP, "kd": L.CFG_KD, "phase_mode": L.CFG_PHASE_MODE, "frequency": L.CFG_FREQ,
    "parameter": L.CFG_PARAM, "clamp": L.CFG_CLAMP, "trip": L.CFG_TRIP, "navg": L.CFG_NAVG,
    "filter_hz": L.CFG_FILTER_HZ, "ring_decimation": L.CFG_RING_DEC,
}
_TARGET_INDEX = {"target_a0": 0}
for _k in range(1, L.NHARM + 1):
    _TARGET_INDEX[f"target_a{_k}"] = _k
    _TARGET_INDEX[f"target_b{_k}"] = L.NHARM + _k


def map_range(rig: str, name: str) -> tuple:
    """A setting's range, from the register map (the datasheet is the one source)."""
    reg_name = {"parameter": "airspeed" if rig == "flutter" else "forcing_amplitude"}.get(name, name)
    if reg_name.startswith("target_"):
        reg_name = "target_a0"
    return BY_NAME[reg_name].range_for(rig)


def _check(name, v, lo, hi):
    if not (lo <= v <= hi):
        raise SettingError(f"{name}: {v:g} outside {lo:g}..{hi:g}")


assert EFFECT_SLOTS == 6
