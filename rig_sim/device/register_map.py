"""The rig's register map: the one description of the device's protocol.

The server's address decoding, the client's accessors (``cbc_controller`` imports
this module and nothing else of ``rig_sim``), the README/docs table and
``rig-sim registers`` are all generated from `REGISTERS`. Adding a register is one
line in `_table()`.

Conventions (as a device datasheet would state them)
- Modbus addresses are 0-based protocol addresses.
- f32: IEEE-754 single precision over two registers, big-endian word order
  (ABCD: high word first; ``mbpoll -B``). u32: same word order.
- str: ASCII, two characters per register, high byte first, NUL padded.
- Input registers (FC4) hold readings; holding registers (FC3/6/16/23) settings.
- Writes outside a setting's range answer ILLEGAL DATA VALUE (03) and change
  nothing; addresses not in the map answer ILLEGAL DATA ADDRESS (02); a multi-
  register write must cover whole values.
- Writes (except to ``control``) need control of the rig: a client that writes
  while nobody holds control takes it implicitly; a write from another client
  while one holds it answers SERVER DEVICE BUSY (06).
- Unit id (`rig-sim serve --unit`, default 1), broadcasts and the TCP gateway
  answer: `addressing.py` and docs/protocol.md.
- The sample ring buffer is a memory-mapped array of int16 records, see
  `RING_*` and docs/registers.md.
Pure Python on purpose: no numpy, no rig internals.
"""

from __future__ import annotations

import json
import struct
from dataclasses import asdict, dataclass

from ..firmware import layout as L

MAP_VERSION = 1
FIRMWARE_VERSION = 100          # 1.00, as major * 100 + minor

NHARM = 7
COEFS = ["a0"] + [f"a{k}" for k in range(1, NHARM + 1)] + [f"b{k}" for k in range(1, NHARM + 1)]
CHANNELS = ("response", "control", "excitation", "second")
CHANNEL_BASE = {"response": 300, "control": 400, "excitation": 500, "second": 600}

RING_BASE = 20000
RING_CAPACITY = 4096
RING_FIELDS = ("seq", "x", "x_dot", "q2", "q2_dot", "target", "control", "parameter", "phase")
RING_RECORD = len(RING_FIELDS)
RING_SCALES = {  # register holding the full scale that int16 32767 stands for
    "x": "fs_x", "x_dot": "fs_x_dot", "q2": "fs_q2", "q2_dot": "fs_q2_dot",
    "target": "fs_x", "control": "fs_control", "parameter": "fs_parameter",
}
CHANNEL_WORDS = 2 + 4 * len(COEFS)   # periods (u32), then mean and variance (f32) per coefficient
MAX_READ = 125       # Modbus limit on registers per read

STATUS_BITS = {
    "armed": 0, "running": 1, "fault": 2, "controlled": 3, "lockstep": 4,
    "phase_locked": 5, "saturating": 6, "estimate_ready": 7,
}
FAULT_WATCHDOG = L.FAULT_WATCHDOG     # the host's heartbeat stopped
FAULT_CODES = {L.FAULT_NONE: "none", L.FAULT_TRIP: "amplitude trip",
               L.FAULT_WATCHDOG: "watchdog (host heartbeat lost)", L.FAULT_DIVERGED: "state diverged"}
COMMANDS = {1: "arm", 2: "disarm", 3: "reset fault", 4: "reset averages"}
CONTROL_VALUES = {0: "free / release", 1: "held by you / claim", 2: "held by another client"}

WIDTH = {"u16": 1, "i16": 1, "u32": 2, "f32": 2, "str16": 8}


@dataclass(frozen=True)
class Register:
    name: str
    table: str            # "input" or "holding"
    address: int
    type: str             # u16, i16, u32, f32, str16
    unit: str
    access: str           # "r" or "rw"
    description: str
    rigs: str = "both"    # "both", "flutter", "oscillator"
    range: object = None  # (lo, hi), or {"flutter": (lo, hi), "oscillator": (lo, hi)}
    integer: bool = False  # a float setting that must be a whole number

    @property
    def width(self) -> int:
        return WIDTH[self.type]

    def range_for(self, rig: str):
        if isinstance(self.range, dict):
            return self.range.get(rig)
        return self.range

    def applies_to(self, rig: str) -> bool:
        return self.rigs in ("both", rig)


def _table() -> list[Register]:
    I, H = "input", "holding"
    r = [
        # ---- identification ------------------------------------------------------
        Register("model", I, 0, "str16", "", "r", "device model: VCL-FLUTTER-2DOF or VCL-EDOSC-1DOF"),
        Register("firmware_version", I, 8, "u16", "", "r", "firmware version, major*100 + minor"),
        Register("map_version", I, 9, "u16", "", "r", "version of this register map"),
        Register("rig_kind", I, 10, "u16", "", "r", "0 flutter aerofoil, 1 electrodynamic oscillator"),
        Register("sample_rate", I, 11, "f32", "Hz", "r", "board loop rate"),
        Register("ring_capacity", I, 13, "u16", "records", "r", "records in the sample ring buffer"),
        Register("ring_record_words", I, 14, "u16", "registers", "r", "registers per ring record"),
        Register("ring_base", I, 15, "u16", "", "r", "address of ring record 0"),
        Register("fs_x", I, 16, "f32", "m", "r", "full scale of x (heave / displacement) and target"),
        Register("fs_x_dot", I, 18, "f32", "m/s", "r", "full scale of x'"),
        Register("fs_q2", I, 20, "f32", "rad", "r", "full scale of the second coordinate (pitch)"),
        Register("fs_q2_dot", I, 22, "f32", "rad/s", "r", "full scale of the second coordinate's rate"),
        Register("fs_control", I, 24, "f32", "N or m/s^2", "r",
                 "actuator saturation = full scale of the control channel"),
        Register("fs_parameter", I, 26, "f32", "m/s or m/s^2", "r", "full scale of the parameter channel"),
        # ---- status and counters ---------------------------------------------------
        Register("status", I, 100, "u16", "bits", "r", "status word, bits in STATUS_BITS"),
        Register("fault_code", I, 101, "u16", "", "r", "latched fault, codes in FAULT_CODES"),
        Register("sample_seq", I, 102, "u32", "samples", "r", "samples since start (ring head)"),
        Register("periods", I, 104, "u32", "", "r", "estimator periods completed"),
        Register("overruns", I, 106, "u32", "", "r", "pacing deadlines the board missed"),
        Register("saturations", I, 108, "u32", "samples", "r", "samples with the output clamped"),
        Register("trips", I, 110, "u16", "", "r", "amplitude trips since start"),
        Register("watchdog_trips", I, 111, "u16", "", "r", "watchdog expiries while armed"),
        Register("ring_head", I, 112, "u32", "records", "r",
                 "records written to the ring buffer; record j sits at ring_base + (j mod capacity) * words"),
        # ---- latest sample ------------------------------------------------------------
        Register("x", I, 200, "f32", "m", "r", "measured heave / displacement"),
        Register("x_dot", I, 202, "f32", "m/s", "r", "measured rate of x"),
        Register("q2", I, 204, "f32", "rad", "r", "measured pitch (aerofoil; 0 on the oscillator)"),
        Register("q2_dot", I, 206, "f32", "rad/s", "r", "measured pitch rate"),
        Register("target_now", I, 208, "f32", "m", "r", "control target at this sample"),
        Register("control_now", I, 210, "f32", "N or m/s^2", "r", "control output after the clamp"),
        Register("excitation_now", I, 212, "f32", "N or m/s^2", "r",
                 "total excitation: forcing + control (oscillator), control (aerofoil)"),
        Register("phase", I, 214, "f32", "rad", "r", "estimator phase in [0, 2 pi)"),
        Register("frequency_estimate", I, 216, "f32", "Hz", "r", "mean period frequency over navg periods"),
        Register("frequency_variance", I, 218, "f32", "Hz^2", "r", "its variance"),
        # ---- settings ------------------------------------------------------------------
        Register("control", H, 0, "u16", "", "rw",
                 "write 1 to claim control, 0 to release; reads 1 yours, 2 another's, 0 free",
                 range=(0, 1)),
        Register("command", H, 1, "u16", "", "rw", "1 arm, 2 disarm, 3 reset fault, 4 reset averages",
                 range=(1, 4)),
        Register("heartbeat", H, 2, "u16", "", "rw",
                 "write a changing value at least every watchdog_timeout", range=(0, 65535)),
        Register("phase_mode", H, 3, "u16", "", "rw",
                 "target phase: 0 forcing phase, 1 locked to the response", range=(0, 1)),
        Register("navg", H, 4, "u16", "periods", "rw", "periods in the running mean/variance",
                 range=(1, 32)),
        Register("ring_decimation", H, 5, "u16", "samples", "rw",
                 "the ring buffer keeps every Nth sample", range=(1, 16)),
        Register("kp", H, 6, "f32", "N/m or (m/s^2)/m", "rw", "proportional gain", range=(-1e6, 1e6)),
        Register("kd", H, 8, "f32", "N s/m or (m/s^2) s/m", "rw", "derivative gain", range=(-1e5, 1e5)),
        Register("frequency", H, 10, "f32", "Hz", "rw",
                 "forcing frequency (oscillator) / phase-lock frequency (aerofoil)",
                 range={"flutter": (0.1, 20.0), "oscillator": (1.0, 100.0)}),
        Register("airspeed", H, 12, "f32", "m/s", "rw", "wind-tunnel airspeed", rigs="flutter",
                 range=(0.0, 40.0)),
        Register("forcing_amplitude", H, 14, "f32", "m/s^2", "rw",
                 "shaker base-acceleration amplitude Phi", rigs="oscillator", range=(0.0, 100.0)),
        Register("clamp", H, 16, "f32", "N or m/s^2", "rw", "output clamp |u| <= clamp",
                 range={"flutter": (0.0, 300.0), "oscillator": (0.0, 100.0)}),
        Register("trip", H, 18, "f32", "m", "rw", "amplitude trip level on |x| (latched fault)",
                 range={"flutter": (0.001, 0.25), "oscillator": (0.0001, 0.02)}),
        Register("filter_hz", H, 20, "f32", "Hz", "rw", "error low-pass cutoff, 0 = off",
                 range=(0.0, 1000.0)),
        Register("watchdog_timeout", H, 22, "f32", "s", "rw",
                 "heartbeat silence that disarms and latches a fault", range=(0.05, 60.0)),
        Register("advance", H, 24, "u32", "samples", "rw",
                 "lockstep only: advance the simulation this many samples, answered when done",
                 range=(1, 1_000_000)),
        Register("noise_seed", H, 28, "u32", "", "rw",
                 "lockstep only: restart the simulation from rest (disarmed, estimator cleared) "
                 "with its noise streams seeded from this value; settings and counters stay",
                 range=(0, 2**31 - 1)),
    ]
    for i, c in enumerate(COEFS):
        r.append(Register(f"target_{c}", H, 30 + 2 * i, "f32", "m", "rw",
                          f"target Fourier coefficient {c} (x* = a0 + sum a_k cos k phi + b_k sin k phi)",
                          range={"flutter": (-0.25, 0.25), "oscillator": (-0.02, 0.02)}))
    for ch in CHANNELS:
        base = CHANNEL_BASE[ch]
        r.append(Register(f"{ch}_periods", I, base, "u32", "", "r",
                          f"period counter when the {ch} estimate was last updated"))
        for i, c in enumerate(COEFS):
            r.append(Register(f"{ch}_mean_{c}", I, base + 2 + 2 * i, "f32", "", "r",
                              f"{ch}: mean of coefficient {c} over navg periods"))
        for i, c in enumerate(COEFS):
            r.append(Register(f"{ch}_var_{c}", I, base + 32 + 2 * i, "f32", "", "r",
                              f"{ch}: variance of coefficient {c} over navg periods"))
    return r


REGISTERS: list[Register] = _table()
BY_NAME: dict[str, Register] = {reg.name: reg for reg in REGISTERS}


def _check_map() -> None:
    for table in ("input", "holding"):
        used: dict[int, str] = {}
        for reg in REGISTERS:
            if reg.table != table:
                continue
            for a in range(reg.address, reg.address + reg.width):
                if a in used:
                    raise AssertionError(f"register overlap at {table} {a}: {used[a]} / {reg.name}")
                if table == "input" and a >= RING_BASE:
                    raise AssertionError(f"{reg.name} overlaps the ring buffer")
                used[a] = reg.name


_check_map()


# ---- codecs -------------------------------------------------------------------------
def encode(reg: Register, value) -> list[int]:
    """Python value -> register words."""
    if reg.type == "u16":
        return [int(value) & 0xFFFF]
    if reg.type == "i16":
        return [int(value) & 0xFFFF]
    if reg.type == "u32":
        v = int(value) & 0xFFFFFFFF
        return [v >> 16, v & 0xFFFF]
    if reg.type == "f32":
        hi, lo = struct.unpack(">HH", struct.pack(">f", float(value)))
        return [hi, lo]
    if reg.type == "str16":
        raw = str(value).encode("ascii")[:16].ljust(16, b"\0")
        return [raw[i] << 8 | raw[i + 1] for i in range(0, 16, 2)]
    raise ValueError(reg.type)


def decode(reg: Register, words) -> object:
    """Register words -> Python value."""
    if reg.type == "u16":
        return int(words[0])
    if reg.type == "i16":
        w = int(words[0])
        return w - 0x10000 if w >= 0x8000 else w
    if reg.type == "u32":
        return int(words[0]) << 16 | int(words[1])
    if reg.type == "f32":
        return struct.unpack(">f", struct.pack(">HH", int(words[0]), int(words[1])))[0]
    if reg.type == "str16":
        raw = b"".join(struct.pack(">H", int(w)) for w in words[:8])
        return raw.rstrip(b"\0").decode("ascii", "replace")
    raise ValueError(reg.type)


def decode_block(table: str, start: int, words) -> dict[str, object]:
    """Decode every whole register of `table` inside words read from `start`."""
    out = {}
    end = start + len(words)
    for reg in REGISTERS:
        if reg.table == table and reg.address >= start and reg.address + reg.width <= end:
            off = reg.address - start
            out[reg.name] = decode(reg, words[off:off + reg.width])
    return out


def ring_address(record: int) -> int:
    """Input-register address of ring record number `record` (0, 1, ... = ring_head - 1)."""
    return RING_BASE + (record % RING_CAPACITY) * RING_RECORD


def channel_of(reg: Register) -> str | None:
    """The Fourier channel whose estimate block holds `reg` (None: not in one)."""
    if reg.table != "input":
        return None
    for ch, base in CHANNEL_BASE.items():
        if base <= reg.address < base + CHANNEL_WORDS:
            return ch
    return None


def f32_words(value: float) -> list[int]:
    return encode(Register("_", "holding", 0, "f32", "", "rw", ""), value)


# ---- documents ------------------------------------------------------------------------
def _fmt_range(reg: Register) -> str:
    if reg.range is None:
        return ""
    if isinstance(reg.range, dict):
        return "; ".join(f"{k}: {lo:g}..{hi:g}" for k, (lo, hi) in reg.range.items())
    lo, hi = reg.range
    return f"{lo:g}..{hi:g}"


def as_json() -> str:
    doc = {
        "map_version": MAP_VERSION, "firmware_version": FIRMWARE_VERSION,
        "word_order": "big-endian (ABCD): high word first", "float": "IEEE-754 float32",
        "status_bits": STATUS_BITS, "fault_codes": FAULT_CODES, "commands": COMMANDS,
        "ring": {"base": RING_BASE, "capacity": RING_CAPACITY, "fields": list(RING_FIELDS),
                 "scales": RING_SCALES, "type": "int16 counts; value = count / 32767 * full scale; "
                 "seq holds the low 16 bits of the sample counter; phase = count/32767*pi + pi"},
        "registers": [asdict(r) for r in REGISTERS],
    }
    return json.dumps(doc, indent=1)


def as_markdown(compact: bool = True) -> str:
    """The datasheet table. `compact` folds the 4 x 31 Fourier registers into rows."""
    lines = [
        f"Register map version {MAP_VERSION} (firmware {FIRMWARE_VERSION // 100}."
        f"{FIRMWARE_VERSION % 100:02d}). Addresses are 0-based protocol addresses. "
        "f32 = IEEE-754 float over two registers, big-endian word order (ABCD, `mbpoll -B`); "
        "u32 the same word order; str16 = 16 ASCII characters, high byte first.",
        "",
        "Unit id, broadcasts and exception replies: see [protocol.md](protocol.md).",
        "",
        "| table | address | name | type | unit | access | range | rigs | description |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for reg in REGISTERS:
        if compact and channel_of(reg) is not None:
            continue
        cells = [reg.table, reg.address, f"`{reg.name}`", reg.type, reg.unit, reg.access,
                 _fmt_range(reg), reg.rigs, reg.description]
        lines.append("| " + " | ".join(str(c).replace("|", "\\|") for c in cells) + " |")
    if compact:
        for ch in CHANNELS:
            b = CHANNEL_BASE[ch]
            lines.append(f"| input | {b} | `{ch}_periods` | u32 |  | r |  | both | period counter of this estimate |")
            lines.append(f"| input | {b + 2}..{b + 31} | `{ch}_mean_<c>` | f32 x 15 |  | r |  | both | "
                         f"mean over navg periods of {ch} coefficient c in {', '.join(COEFS)} |")
            lines.append(f"| input | {b + 32}..{b + 61} | `{ch}_var_<c>` | f32 x 15 |  | r |  | both | "
                         f"variance of the same |")
    end = RING_BASE + RING_CAPACITY * RING_RECORD - 1
    lines += [
        f"| input | {RING_BASE}..{end} | ring buffer | int16 x {RING_RECORD} x {RING_CAPACITY} |  | r |  | both | "
        f"sample records ({', '.join(RING_FIELDS)}) |",
        "",
        "Status bits: " + ", ".join(f"{b} = {n}" for n, b in STATUS_BITS.items()) + ".  ",
        "Fault codes: " + ", ".join(f"{c} = {n}" for c, n in FAULT_CODES.items()) + ".  ",
        "Commands: " + ", ".join(f"{c} = {n}" for c, n in COMMANDS.items()) + ".  ",
        "Fourier channels: response = heave / displacement (m); control = control output after the "
        "clamp; excitation = total excitation (forcing + control for the oscillator); second = pitch "
        "(rad, aerofoil only). Coefficients: x = a0 + sum_k a_k cos(k phi) + b_k sin(k phi) over the "
        "estimator phase phi.  ",
        f"Ring buffer: record j (j = 0, 1, ..., `ring_head` - 1) at {RING_BASE} + (j mod {RING_CAPACITY}) * "
        f"{RING_RECORD}; one record every `ring_decimation` samples; int16 counts, value = count / 32767 * "
        "full scale (registers fs_*); `seq` is the sample number mod 65536 (time = sample number / "
        "sample_rate); phase = count / 32767 * pi + pi. A client reads `ring_head` and pulls the records "
        "behind it; a record more than the capacity behind the head has been overwritten (a gap the "
        "client can count).",
    ]
    return "\n".join(lines) + "\n"
