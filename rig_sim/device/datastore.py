"""Register access: decodes Modbus reads and writes against the register map and
applies them to the board. Validation happens before anything changes, so a bad
write (unknown address, partial value, out-of-range value, not your control)
leaves every setting as it was.

The protocol layer calls `async_getValues` / `async_setValues` (the interface
pymodbus 3.16's request PDUs call on the server context), tagged with the
calling connection through `CURRENT_CLIENT`.
"""

from __future__ import annotations

import contextvars
import math
import threading

import numpy as np
from pymodbus.constants import ExcCodes

from ..firmware import layout as L
from ..firmware.board import Board, SettingError, StateError
from . import register_map as M

# Set by the request handler for the duration of one request: who is asking.
CURRENT_CLIENT: contextvars.ContextVar[object] = contextvars.ContextVar("rig_client", default=None)

_HOLDING_FC = {3, 6, 16, 22, 23}
_INPUT_FC = {4}
_RING_END = M.RING_BASE + M.RING_CAPACITY * M.RING_RECORD


def _index(table: str) -> dict[int, tuple[M.Register, int]]:
    idx = {}
    for reg in M.REGISTERS:
        if reg.table == table:
            for off in range(reg.width):
                idx[reg.address + off] = (reg, off)
    return idx


_INPUT_INDEX = _index("input")
_HOLDING_INDEX = _index("holding")

# holding-register name -> board setting name
_SETTING = {name: name for name in (
    "kp", "kd", "frequency", "clamp", "trip", "filter_hz", "watchdog_timeout", "navg",
    "phase_mode", "ring_decimation", "noise_seed")}
_SETTING.update({"airspeed": "parameter", "forcing_amplitude": "parameter"})
for _c in M.COEFS:
    _SETTING[f"target_{_c}"] = f"target_{_c}"


class RigRegisters:
    """The device's register space bound to one board."""

    def __init__(self, board: Board, lockstep: bool = False):
        self.board = board
        self.rig = board.spec.kind
        self.lockstep = lockstep
        self.running = False          # set by the pacer while it advances time
        self.owner: object = None     # connection holding control
        self.heartbeat_value = 0
        self.advance_value = 0
        self.lock = threading.RLock()
        self.identity = {
            "model": board.spec.model, "firmware_version": M.FIRMWARE_VERSION,
            "map_version": M.MAP_VERSION, "rig_kind": 0 if self.rig == "flutter" else 1,
            "sample_rate": board.rate, "ring_capacity": M.RING_CAPACITY,
            "ring_record_words": M.RING_RECORD, "ring_base": M.RING_BASE,
            "fs_x": board.spec.full_scale[0], "fs_x_dot": board.spec.full_scale[1],
            "fs_q2": board.spec.full_scale[2], "fs_q2_dot": board.spec.full_scale[3],
            "fs_control": board.spec.saturation, "fs_parameter": board.spec.param_full_scale,
        }

    # ---- pymodbus context interface ---------------------------------------------------
    def device_ids(self) -> list[int]:
        return [0]

    async def async_getValues(self, device_id, func_code, address, count=1):
        return self.read(func_code, address, count, CURRENT_CLIENT.get())

    async def async_setValues(self, device_id, func_code, address, values):
        return self.write(func_code, address, list(values), CURRENT_CLIENT.get())

    # ---- ownership ---------------------------------------------------------------------
    def release_if_owner(self, client) -> None:
        with self.lock:
            if client is not None and self.owner is client:
                self.owner = None

    def free_control(self) -> None:
        with self.lock:
            self.owner = None

    # ---- reads -----------------------------------------------------------------------------
    def read(self, func_code, address, count, client=None):
        if func_code in _INPUT_FC:
            table, index = "input", _INPUT_INDEX
        elif func_code in _HOLDING_FC:
            table, index = "holding", _HOLDING_INDEX
        else:
            return ExcCodes.ILLEGAL_ADDRESS   # no coils or discrete inputs on this device
        if count < 1 or address < 0 or address + count > 0x10000:
            return ExcCodes.ILLEGAL_ADDRESS
        with self.lock, self.board.lock:
            if table == "input" and M.RING_BASE <= address and address + count <= _RING_END:
                off = address - M.RING_BASE
                return self.board.ring.reshape(-1)[off:off + count].tolist()
            out: list[int] = []
            cache: dict[str, list[int]] = {}
            for a in range(address, address + count):
                hit = index.get(a)
                if hit is None:
                    return ExcCodes.ILLEGAL_ADDRESS
                reg, off = hit
                if not reg.applies_to(self.rig):
                    return ExcCodes.ILLEGAL_ADDRESS
                words = cache.get(reg.name)
                if words is None:
                    words = M.encode(reg, self._value(reg, client))
                    cache[reg.name] = words
                out.append(words[off])
            return out

    def _value(self, reg: M.Register, client):
        b = self.board
        name = reg.name
        if name in self.identity:
            return self.identity[name]
        if reg.table == "holding":
            if name == "control":
                if self.owner is None:
                    return 0
                return 1 if self.owner is client else 2
            if name == "command":
                return 0
            if name == "heartbeat":
                return self.heartbeat_value
            if name == "advance":
                return self.advance_value
            return b.get(_SETTING[name])
        ic, fw = b.ic, b.fw
        if name == "status":
            return self.status_word()
        if name == "fault_code":
            return int(ic[L.IC_FAULT])
        if name == "sample_seq":
            return int(ic[L.IC_SEQ])
        if name == "ring_head":
            return int(ic[L.IC_RING_HEAD])
        if name == "periods":
            return int(ic[L.IC_PERIODS])
        if name == "overruns":
            return b.overruns
        if name == "saturations":
            return int(ic[L.IC_SAT])
        if name == "trips":
            return int(ic[L.IC_TRIPS])
        if name == "watchdog_trips":
            return b.watchdog_trips
        simple = {"x": fw[L.FW_XM], "x_dot": fw[L.FW_XM + 1], "q2": fw[L.FW_XM + 2],
                  "q2_dot": fw[L.FW_XM + 3], "target_now": fw[L.FW_TGT],
                  "control_now": fw[L.FW_U], "excitation_now": fw[L.FW_EXC],
                  "phase": fw[L.FW_TH_EST], "frequency_estimate": b.fmean[0],
                  "frequency_variance": b.fvar[0]}
        if name in simple:
            return float(simple[name])
        ch_name, _, rest = name.partition("_")
        ch = M.CHANNELS.index(ch_name)
        if rest == "periods":
            return int(ic[L.IC_PERIODS])
        kind, _, coef = rest.partition("_")
        k = M.COEFS.index(coef)
        return float((b.cmean if kind == "mean" else b.cvar)[ch, k])

    def status_word(self) -> int:
        b = self.board
        bits = {
            "armed": b.armed, "running": self.running, "fault": b.fault != 0,
            "controlled": self.owner is not None, "lockstep": self.lockstep,
            "phase_locked": b.cfg[L.CFG_PHASE_MODE] > 0.5,
            "saturating": abs(b.fw[L.FW_U]) >= min(b.cfg[L.CFG_CLAMP], b.spec.saturation) > 0
            and b.armed,
            "estimate_ready": b.ic[L.IC_HIST_N] >= b.cfg[L.CFG_NAVG],
        }
        return sum(1 << M.STATUS_BITS[k] for k, v in bits.items() if v)

    # ---- writes -----------------------------------------------------------------------------
    def write(self, func_code, address, values, client=None):
        if func_code not in _HOLDING_FC:
            return ExcCodes.ILLEGAL_ADDRESS
        count = len(values)
        if count < 1 or address < 0 or address + count > 0x10000:
            return ExcCodes.ILLEGAL_ADDRESS
        # 1. every register written must be whole and exist for this rig
        items: list[tuple[M.Register, list[int]]] = []
        a = address
        while a < address + count:
            hit = _HOLDING_INDEX.get(a)
            if hit is None:
                return ExcCodes.ILLEGAL_ADDRESS
            reg, off = hit
            if off != 0 or a + reg.width > address + count or not reg.applies_to(self.rig):
                return ExcCodes.ILLEGAL_ADDRESS
            items.append((reg, values[a - address:a - address + reg.width]))
            a += reg.width
        # 2. decode and range-check every value before changing anything
        decoded = []
        for reg, words in items:
            value = M.decode(reg, words)
            rng = reg.range_for(self.rig)
            if isinstance(value, float) and not math.isfinite(value):
                return ExcCodes.ILLEGAL_VALUE
            if rng is not None and not (rng[0] <= value <= rng[1]):
                return ExcCodes.ILLEGAL_VALUE
            decoded.append((reg, value))
        with self.lock, self.board.lock:
            # 3. control of the rig
            names = [reg.name for reg, _ in decoded]
            if any(n != "control" for n in names):
                if self.owner is None and client is not None:
                    self.owner = client            # implicit claim by the first writer
                    self.board.heartbeat()
                elif self.owner is not client:
                    return ExcCodes.DEVICE_BUSY
            if ("advance" in names or "noise_seed" in names) and not self.lockstep:
                return ExcCodes.ILLEGAL_FUNCTION   # only meaningful in lockstep
            for reg, value in decoded:
                if reg.name == "command" and value == 1 and self.board.fault != 0:
                    return ExcCodes.DEVICE_FAILURE  # armed refused while a fault is latched
            # 4. apply
            for reg, value in decoded:
                rc = self._apply(reg, value, client)
                if rc is not None:
                    return rc
        return None

    def _apply(self, reg: M.Register, value, client):
        b = self.board
        name = reg.name
        if name == "control":
            if value == 1:
                if self.owner is None or self.owner is client:
                    self.owner = client
                    b.heartbeat()
                    return None
                return ExcCodes.DEVICE_BUSY
            if self.owner is None or self.owner is client:
                self.owner = None
                return None
            return ExcCodes.DEVICE_BUSY
        if name == "command":
            try:
                {1: b.arm, 2: b.disarm, 3: b.reset_fault, 4: b.reset_averages}[int(value)]()
            except StateError:
                return ExcCodes.DEVICE_FAILURE
            return None
        if name == "heartbeat":
            self.heartbeat_value = int(value)
            b.heartbeat()
            return None
        if name == "advance":
            self.advance_value = int(value)
            self.step_lockstep(int(value))
            return None
        try:
            b.set(_SETTING[name], float(value))
        except SettingError:
            return ExcCodes.ILLEGAL_VALUE
        return None

    def step_lockstep(self, nsamples: int) -> None:
        """Advance the simulation in lockstep; the watchdog runs on simulated time."""
        chunk = max(1, int(0.05 * self.board.rate))
        left = nsamples
        while left > 0:
            n = min(chunk, left)
            self.board.advance(n)
            left -= n
            if (self.owner is not None or self.board.armed) and self.board.check_watchdog(lockstep=True):
                self.owner = None


def ring_records(words, n_records: int) -> np.ndarray:
    """Client-side helper: raw ring words -> (n, RING_RECORD) int16 array."""
    return np.asarray(words, dtype=np.uint16).reshape(n_records, M.RING_RECORD).view(np.int16)
