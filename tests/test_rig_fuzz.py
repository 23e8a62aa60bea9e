"""Robustness: the service under a storm of random and mutated Modbus frames.

10,000 frames over Modbus TCP (flutter rig) and 10,000 over Modbus RTU through a
socat pty pair (oscillator rig), from a seeded generator: random bytes; frames
with mutated function codes, unit ids, addresses, counts, byte counts and CRCs;
truncated and over-long frames; bit flips; writes to every holding register with
NaN, infinities, out-of-range and random garbage values, partial float writes,
writes to unmapped addresses and multi-register writes in which one value is
bad. Every frame is checked against a model of the datasheet (`Datasheet`
below) before it is sent: frames that the datasheet says would legitimately
change something (a valid in-range write) are not sent, so that **no setting may
change** during the storm.

Throughout, a real client (`RigClient`, pymodbus) interleaves valid requests:
it reads the identification, every holding register (compared with the snapshot
taken before the storm) and the status/counter block, writes a setting, reads it
back and restores it. Each well-formed frame's own answer is also checked: the
exception code the datasheet prescribes (02 unmapped or partial value, 03 out of
range or inconsistent counts, 01 undecodable), holding-register reads returning
the snapshot words, and on RTU no answer at all to a frame with a bad CRC. At
the end the rig process must still be running.

The rigs run in --lockstep so that nothing but a write could change a setting.

RTU timing. A pty has no inter-frame gaps, and pymodbus's RTU framer drops its
whole buffer on a CRC failure, so frames must not run together. Each fuzz frame
goes out as soon as the previous answer is in or, for a frame that gets none,
after 1 ms of line quiet; such a frame is followed by a burst of line noise
(270 x 0xFF, longer than any frame: whatever partial frame the device holds is
completed with it and fails its CRC — never completed by the next real frame,
which after a chance CRC match could make a valid write) or, now and then, by
40 ms of silence, after which the device must have dropped any partial frame
(server.RTU_FRAME_SILENCE_S = 20 ms, the inter-frame silence rule of the Modbus
serial-line spec) and must answer the next frame. A frame sent while the device
may still hold something unanswered may go unanswered (counted as "relaxed").
A frame the device should have answered but did not is sent once more after
another silence (on a loaded host the device's process may not run during a
silence, and a pty keeps no timing) and must then be answered. Before every
interleaved client check the line is silent for 40 ms.
"""

from __future__ import annotations

import collections
import math
import os
import select
import socket
import struct
import time
import tty
from dataclasses import dataclass

import numpy as np

from cbc_controller.client import RigClient
from rig_sim.device import register_map as M

SEED = 20240607
N_FRAMES = 10_000
CHECK_EVERY = 200           # fuzz frames between interleaved client checks
RTU_SILENCE_S = 0.04        # line silence before a client check (device discards partials after 20 ms)
RTU_QUIET_S = 0.001         # line quiet that ends the wait for an unanswered frame
NOISE = b"\xff" * 270       # RTU line noise: longer than the longest frame (256 bytes)

MODEL = {"flutter": "VCL-FLUTTER-2DOF", "oscillator": "VCL-EDOSC-1DOF"}


# ---- CRC-16/MODBUS (polynomial 0xA001 reflected, init 0xFFFF, low byte first) ----------
def _crc_table():
    table = []
    for b in range(256):
        c = b
        for _ in range(8):
            c = (c >> 1) ^ 0xA001 if c & 1 else c >> 1
        table.append(c)
    return table


_CRC_TABLE = _crc_table()


def crc16(data: bytes) -> bytes:
    c = 0xFFFF
    for b in data:
        c = (c >> 8) ^ _CRC_TABLE[(c ^ b) & 0xFF]
    return struct.pack("<H", c)


def test_crc_reference_value():
    # the worked example of the Modbus serial-line guide: 01 03 00 00 00 01 -> 84 0A
    assert crc16(bytes.fromhex("010300000001")) == bytes.fromhex("840A")


# ---- the datasheet as a model ------------------------------------------------------------------
EXC, OK, ANY, NONE = "exc", "ok", "any", "none"


class Datasheet:
    """What the register map says a request does: which frames would change the
    rig (valid writes) and which answer each well-formed request must get."""

    def __init__(self, rig: str):
        self.rig = rig
        self.holding = [r for r in M.REGISTERS if r.table == "holding" and r.applies_to(rig)]
        self.index = {t: {a: (r, a - r.address) for r in M.REGISTERS if r.table == t and r.applies_to(rig)
                          for a in range(r.address, r.address + r.width)} for t in ("input", "holding")}
        self.snapshot: dict[int, int] = {}      # holding address -> word, filled before the storm

    # the rules of the datasheet ---------------------------------------------------------------
    def read_code(self, table: str, address: int, count: int):
        end = M.RING_BASE + M.RING_CAPACITY * M.RING_RECORD
        if table == "input" and M.RING_BASE <= address and address + count <= end:
            return None
        if all(a in self.index[table] for a in range(address, address + count)):
            return None
        return 2

    @staticmethod
    def value(reg: M.Register, words):
        if reg.type == "f32":
            return struct.unpack(">f", struct.pack(">HH", *words))[0]
        if reg.type == "u32":
            return words[0] << 16 | words[1]
        return words[0]

    def write_code(self, address: int, words: list[int]):
        """None: the write is valid and would be applied; else its exception code."""
        count = len(words)
        if count < 1 or address + count > 0x10000:
            return 2
        items, a = [], address
        while a < address + count:
            hit = self.index["holding"].get(a)
            if hit is None:
                return 2
            reg, off = hit
            if off != 0 or a + reg.width > address + count:
                return 2                                # not a whole value
            items.append((reg, words[a - address:a - address + reg.width]))
            a += reg.width
        for reg, w in items:
            v = self.value(reg, w)
            if isinstance(v, float) and not math.isfinite(v):
                return 3
            lo, hi = reg.range_for(self.rig)
            if not lo <= v <= hi:
                return 3
        return None

    def classify(self, pdu: bytes):
        """(changes, expectation) for a PDU as the device will decode it."""
        if not pdu:
            return False, (NONE,)
        fc, d = pdu[0], pdu[1:]
        if fc in (3, 4):
            if len(d) < 4:
                return False, (EXC, 1)
            address, count = struct.unpack(">HH", d[:4])
            if not 1 <= count <= 125:
                return False, (EXC, 1)
            table = "holding" if fc == 3 else "input"
            if self.read_code(table, address, count):
                return False, (EXC, 2)
            data = [self.snapshot[a] for a in range(address, address + count)] if fc == 3 else None
            return False, (OK, fc, data)
        if fc == 6:
            if len(d) < 4:
                return False, (EXC, 1)
            address, word = struct.unpack(">HH", d[:4])
            code = self.write_code(address, [word])
            return (True, None) if code is None else (False, (EXC, code))
        if fc == 16:
            if len(d) < 5:
                return False, (EXC, 1)
            address, count, nbytes = struct.unpack(">HHB", d[:5])
            if not 1 <= count <= 123:
                return False, (EXC, 3)
            if nbytes != 2 * count or len(d) - 5 != nbytes:
                return False, (EXC, 3)
            words = list(struct.unpack(f">{count}H", d[5:5 + nbytes]))
            code = self.write_code(address, words)
            return (True, None) if code is None else (False, (EXC, code))
        if fc == 22:
            if len(d) < 6:
                return False, (EXC, 1)
            address = struct.unpack(">H", d[:2])[0]
            if self.read_code("holding", address, 1):
                return False, (EXC, 2)
            reg, _ = self.index["holding"][address]
            if reg.width == 1:
                return True, None           # might produce a valid value: never sent
            return False, (EXC, 2)          # a one-word write into a wider value
        if fc == 23:
            if len(d) < 9:
                return False, (EXC, 1)
            ra, rc, wa, wc, nbytes = struct.unpack(">HHHHB", d[:9])
            if not (1 <= rc <= 125 and 1 <= wc <= 125):
                return False, (EXC, 1)
            if not 1 <= wc <= 121 or nbytes != 2 * wc or len(d) - 9 != nbytes:
                return False, (EXC, 3)
            if self.read_code("holding", ra, rc):
                return False, (EXC, 2)
            code = self.write_code(wa, list(struct.unpack(f">{wc}H", d[9:9 + nbytes])))
            return (True, None) if code is None else (False, (EXC, code))
        if fc in KNOWN_FC or fc > 0x80:
            return False, (ANY,)            # coils, diagnostics, identification...: no setting
        return False, (EXC, 1)              # unknown function


# function codes pymodbus 3.16 decodes as requests
KNOWN_FC = {1, 2, 3, 4, 5, 6, 7, 8, 11, 12, 15, 16, 17, 20, 21, 22, 23, 24, 43}


# ---- frame generator --------------------------------------------------------------------------
@dataclass
class Frame:
    kind: str
    pdu: bytes
    expect: tuple          # (EXC, code) | (OK, fc, data) | (ANY,) | (NONE,)


class Fuzzer:
    """Seeded PDUs designed to be invalid; `Datasheet.classify` vetoes any that is not."""

    KINDS = ["bad_value", "multi_one_bad", "partial", "unmapped", "counts", "fc23", "fc22",
             "mutated_fc", "random_pdu", "bit_flip", "reads", "other_fc"]
    WEIGHTS = [26, 10, 8, 8, 8, 6, 3, 8, 6, 7, 6, 4]

    def __init__(self, rig: str, sheet: Datasheet, seed: int):
        self.rig, self.sheet = rig, sheet
        self.rng = np.random.default_rng(seed)
        self.p = np.array(self.WEIGHTS, float) / sum(self.WEIGHTS)
        self.rr = 0                                     # round robin over the holding registers
        self.vetoed = 0
        self.runs = self._runs()
        self.gaps = [a for a in range(0, 70) if a not in sheet.index["holding"]]

    def _runs(self):
        """Maximal runs of adjacent holding registers of this rig."""
        runs, cur = [], []
        for reg in sorted(self.sheet.holding, key=lambda r: r.address):
            if cur and cur[-1].address + cur[-1].width != reg.address:
                runs.append(cur)
                cur = []
            cur.append(reg)
        runs.append(cur)
        return runs

    # values ------------------------------------------------------------------------------------
    def words_of(self, reg: M.Register, v) -> list[int]:
        if reg.type == "f32":
            return list(struct.unpack(">HH", struct.pack(">f", v)))
        if reg.type == "u32":
            return [v >> 16 & 0xFFFF, v & 0xFFFF]
        return [int(v) & 0xFFFF]

    def valid_value(self, reg: M.Register):
        lo, hi = reg.range_for(self.rig)
        if reg.type == "f32":
            return float(self.rng.uniform(lo, hi)) if self.rng.random() < 0.8 else float(self.rng.choice([lo, hi]))
        return int(self.rng.integers(lo, int(hi) + 1))

    def bad_words(self, reg: M.Register) -> list[int] | None:
        """Words of an invalid value for reg (None: reg has none, e.g. heartbeat)."""
        lo, hi = reg.range_for(self.rig)
        rng = self.rng
        for _ in range(50):
            if reg.type == "f32":
                k = rng.integers(6)
                span = hi - lo
                if k == 0:      # NaN, quiet or signalling, random payload and sign
                    bits = int(rng.integers(2)) << 31 | 0xFF << 23 | int(rng.integers(1, 1 << 23))
                    w = [bits >> 16, bits & 0xFFFF]
                elif k == 1:    # infinities
                    w = [0x7F80 | (0x8000 if rng.integers(2) else 0), 0]
                elif k == 2:
                    w = self.words_of(reg, hi + span * 10 ** rng.uniform(-4, 3))
                elif k == 3:
                    w = self.words_of(reg, lo - span * 10 ** rng.uniform(-4, 3))
                elif k == 4:    # the largest finite floats
                    w = self.words_of(reg, float(rng.choice([3.4028234e38, -3.4028234e38])))
                else:           # garbage bits
                    w = [int(x) for x in rng.integers(0, 1 << 16, 2)]
            elif reg.type == "u32":
                w = self.words_of(reg, 0 if rng.random() < 0.3 else int(rng.integers(int(hi) + 1, 1 << 32)))
            else:
                choices = []
                if hi < 0xFFFF:
                    choices.append(int(rng.integers(int(hi) + 1, 0x10000)))
                if lo > 0:
                    choices.append(int(rng.integers(0, int(lo))))
                if not choices:
                    return None
                w = [choices[int(rng.integers(len(choices)))]]
            if self.sheet.write_code(reg.address, w) == 3:
                return w
        return None

    # frames --------------------------------------------------------------------------------------
    @staticmethod
    def fc16(address: int, words: list[int], count: int | None = None, nbytes: int | None = None) -> bytes:
        count = len(words) if count is None else count
        nbytes = 2 * len(words) if nbytes is None else nbytes
        return struct.pack(">BHHB", 16, address, count & 0xFFFF, nbytes & 0xFF) + \
            b"".join(struct.pack(">H", w) for w in words)

    @staticmethod
    def fc6(address: int, word: int) -> bytes:
        return struct.pack(">BHH", 6, address, word)

    def valid_write(self) -> bytes:
        """A valid in-range write (a base for mutations; never sent as is)."""
        run = self.runs[int(self.rng.integers(len(self.runs)))]
        i = int(self.rng.integers(len(run)))
        j = min(len(run), i + 1 + int(self.rng.integers(4)))
        words = []
        for reg in run[i:j]:
            words += self.words_of(reg, self.valid_value(reg))
        return self.fc16(run[i].address, words)

    def make(self, kind: str) -> bytes:
        rng, sheet = self.rng, self.sheet
        if kind == "bad_value":         # every holding register in turn, invalid values
            reg = self.sheet.holding[self.rr % len(self.sheet.holding)]
            self.rr += 1
            w = self.bad_words(reg)
            if w is None:               # heartbeat: every u16 is valid -> write half of it with a bad neighbour
                return self.make("multi_one_bad")
            if reg.width == 1 and rng.random() < 0.4:
                return self.fc6(reg.address, w[0])
            return self.fc16(reg.address, w)
        if kind == "multi_one_bad":     # valid values and one bad one: all or nothing
            multi = [r for r in self.runs if len(r) > 1]
            run = multi[int(rng.integers(len(multi)))]
            i = int(rng.integers(len(run) - 1))
            regs = run[i:min(len(run), i + 2 + int(rng.integers(6)))]
            bad_choices = [k for k, r in enumerate(regs) if self.bad_words(r) is not None]
            bad = bad_choices[int(rng.integers(len(bad_choices)))] if bad_choices and rng.random() < 0.8 else None
            words = []
            for k, reg in enumerate(regs):
                words += self.bad_words(reg) if k == bad else self.words_of(reg, self.valid_value(reg))
            if bad is None:             # all valid, plus one word past them: half a value or a gap
                words.append(int(rng.integers(0x10000)))
            return self.fc16(regs[0].address, words)
        if kind == "partial":           # half a float / u32
            wide = [r for r in sheet.holding if r.width == 2]
            reg = wide[int(rng.integers(len(wide)))]
            k = rng.integers(4)
            w = [int(x) for x in rng.integers(0, 1 << 16, 3)]
            if k == 0:
                return self.fc6(reg.address + int(rng.integers(2)), w[0])
            if k == 1:
                return self.fc16(reg.address, w[:1])
            if k == 2:
                return self.fc16(reg.address + 1, w[:2])
            return self.fc16(reg.address + 1, w[:1])
        if kind == "unmapped":
            k = rng.integers(4)
            if k == 0:
                a = self.gaps[int(rng.integers(len(self.gaps)))]
            elif k == 1:
                a = int(rng.integers(70, 0x10000))
            elif k == 2:                # the other rig's parameter register
                a = M.BY_NAME["forcing_amplitude" if self.rig == "flutter" else "airspeed"].address
            else:                       # running past the end of the address space
                a = int(rng.integers(0xFFF0, 0x10000))
                return self.fc16(a, [int(x) for x in rng.integers(0, 1 << 16, 0x10001 - a + int(rng.integers(4)))])
            n = int(rng.integers(1, 5))
            if n == 1 and rng.random() < 0.5:
                return self.fc6(a, int(rng.integers(0x10000)))
            return self.fc16(a, [int(x) for x in rng.integers(0, 1 << 16, n)])
        if kind == "counts":            # a valid write with inconsistent count / byte count / payload
            base = self.valid_write()
            address, count, nbytes = struct.unpack(">HHB", base[1:6])
            words = list(struct.unpack(f">{count}H", base[6:]))
            k = rng.integers(5)
            if k == 0:
                return self.fc16(address, words, count=int(rng.choice([0, 124, 125, 255, 0xFFFF])))
            if k == 1:
                return self.fc16(address, words, nbytes=int(rng.choice([b for b in range(256) if b != nbytes])))
            if k == 2:
                return base[:-1 - int(rng.integers(min(4, len(base) - 6)))]      # payload shorter than byte count
            if k == 3:
                return base + bytes(rng.integers(0, 256, int(rng.integers(1, 5)), dtype=np.uint8))
            return self.fc16(address, words, count=count + 1, nbytes=2 * count + 2)   # claims one word more
        if kind == "fc23":
            base = self.valid_write()
            address, count, _ = struct.unpack(">HHB", base[1:6])
            words = base[6:]
            k = rng.integers(5)
            ra, rc = 0, 10
            if k == 4:                  # unmapped read part and inconsistent byte count: 03 first
                ra = self.gaps[int(rng.integers(len(self.gaps)))]
                return struct.pack(">BHHHHB", 23, ra, 2, address, count, (2 * count + 2) & 0xFF) + words
            if k == 0:                  # valid write, unmapped read part
                ra = self.gaps[int(rng.integers(len(self.gaps)))]
                rc = int(rng.integers(1, 5))
            elif k == 1:                # read count 0 or > 125
                rc = int(rng.choice([0, 126, 200]))
            elif k == 2:                # write byte count inconsistent
                return struct.pack(">BHHHHB", 23, ra, rc, address, count, (2 * count + 1) & 0xFF) + words
            else:                       # valid read, invalid write
                reg = sheet.holding[int(rng.integers(len(sheet.holding)))]
                w = self.bad_words(reg) or [0]
                return struct.pack(">BHHHHB", 23, 0, 6, reg.address, len(w), 2 * len(w)) + \
                    b"".join(struct.pack(">H", x) for x in w)
            return struct.pack(">BHHHHB", 23, ra, rc, address, count, 2 * count) + words
        if kind == "fc22":
            wide = [r for r in sheet.holding if r.width == 2]
            a = wide[int(rng.integers(len(wide)))].address + int(rng.integers(2)) if rng.random() < 0.7 \
                else self.gaps[int(rng.integers(len(self.gaps)))]
            return struct.pack(">BHHH", 22, a, *[int(x) for x in rng.integers(0, 1 << 16, 2)])
        if kind == "mutated_fc":
            base = self.make(str(rng.choice(["bad_value", "partial", "counts", "reads"]))) \
                if rng.random() < 0.5 else self.valid_write()
            fc = int(rng.choice(sorted(KNOWN_FC))) if rng.random() < 0.5 else int(rng.integers(256))
            return bytes([fc]) + base[1:]
        if kind == "random_pdu":
            n = int(rng.integers(1, 40))
            pdu = bytes(rng.integers(0, 256, n, dtype=np.uint8))
            if rng.random() < 0.5:      # a plausible function code
                pdu = bytes([int(rng.choice([3, 4, 6, 16, 22, 23]))]) + pdu[1:]
            return pdu
        if kind == "bit_flip":
            pdu = bytearray(self.valid_write())
            for _ in range(int(rng.integers(1, 4))):
                i = int(rng.integers(len(pdu)))
                pdu[i] ^= 1 << int(rng.integers(8))
            return bytes(pdu)
        if kind == "reads":
            fc = int(rng.choice([3, 4]))
            k = rng.integers(4)
            if k == 0:                  # a valid read
                if fc == 3:
                    run = self.runs[int(rng.integers(len(self.runs)))]
                    a = run[0].address
                    n = int(rng.integers(1, run[-1].address + run[-1].width - a + 1))
                else:
                    a, n = int(rng.choice([0, 100, 200, 300, M.RING_BASE])), int(rng.integers(1, 14))
                return struct.pack(">BHH", fc, a, n)
            if k == 1:
                return struct.pack(">BHH", fc, int(rng.integers(0x10000)), int(rng.integers(1, 126)))
            if k == 2:
                return struct.pack(">BHH", fc, 0, int(rng.choice([0, 126, 0xFFFF])))
            return struct.pack(">BHH", fc, self.gaps[int(rng.integers(len(self.gaps)))], 1)
        if kind == "other_fc":          # coils, diagnostics, device identification, files, FIFO
            fc = int(rng.choice([1, 2, 5, 7, 8, 11, 12, 15, 17, 20, 21, 24, 43]))
            return bytes([fc]) + bytes(rng.integers(0, 256, int(rng.integers(0, 12)), dtype=np.uint8))
        raise ValueError(kind)

    def next(self) -> Frame:
        while True:
            kind = str(self.rng.choice(self.KINDS, p=self.p))
            pdu = self.make(kind)
            changes, expect = self.sheet.classify(pdu)
            if changes:
                self.vetoed += 1
                continue
            return Frame(kind, pdu, expect)

    def safe(self, pdu: bytes) -> bool:
        """The device must not change for any prefix or extension of a PDU
        (transport mutations cut or extend what the device sees)."""
        views = [pdu[:k] for k in range(1, len(pdu))] + [pdu + bytes(self.rng.integers(0, 256, 8, dtype=np.uint8))]
        return not any(self.sheet.classify(v)[0] for v in views)


# ---- interleaved valid client ------------------------------------------------------------------
def holding_runs(sheet: Datasheet):
    addrs = sorted(sheet.index["holding"])
    runs, start = [], addrs[0]
    for a, b in zip(addrs, addrs[1:] + [None]):
        if b != a + 1:
            runs.append((start, a + 1 - start))
            start = b
    return runs


class Checker:
    """A real client (RigClient over pymodbus) doing valid work between fuzz bursts."""

    def __init__(self, url: str, rig: str, sheet: Datasheet):
        self.client = RigClient(url, timeout=2.0, retries=1)
        ident = self.client.connect()
        assert ident["model"] == MODEL[rig]
        self.rig, self.sheet = rig, sheet
        self.runs = holding_runs(sheet)
        self.holding0 = self.holding()
        sheet.snapshot = dict(self.holding0)
        assert self.holding0[0] == 0                     # control free
        self.status0 = self.client.read_words("input", 100, 14)   # status .. ring_head
        self.ident0 = self.client.read_words("input", 0, 28)
        self.checks = 0

    def holding(self) -> dict[int, int]:
        out = {}
        for start, n in self.runs:
            for i, w in enumerate(self.client.read_words("holding", start, n)):
                out[start + i] = w
        return out

    def check(self, where: str):
        c = self.client
        assert c.read_words("input", 0, 28) == self.ident0, where
        now = self.holding()
        changed = {a: (self.holding0[a], now[a]) for a in now if now[a] != self.holding0[a]}
        assert not changed, f"{where}: holding registers changed by invalid frames: {changed}"
        assert c.read_words("input", 100, 14) == self.status0, f"{where}: status/counters changed"
        # a valid write still works, reads back exactly, and is undone
        f0 = c.get("frequency")
        lo, hi = M.BY_NAME["frequency"].range_for(self.rig)
        f1 = float(np.float32(lo + (hi - lo) * (0.25 + 0.5 * (self.checks % 7) / 7)))
        c.write(frequency=f1)
        assert c.get("frequency") == f1, where
        c.write(frequency=f0)
        c.write(control=0)
        assert self.holding() == self.holding0, where
        self.checks += 1

    def close(self):
        self.client.close()


def _expect_ok(expect, fc, body, where):
    """Check one answer (function code + data) against the expectation."""
    if expect[0] == EXC:
        assert fc & 0x80, f"{where}: expected exception {expect[1]}, got function {fc} {body.hex()}"
        assert body[:1] == bytes([expect[1]]), f"{where}: expected exception {expect[1]}, got {body.hex()}"
    elif expect[0] == OK:
        assert fc == expect[1], f"{where}: expected a normal answer to {expect[1]}, got {fc} {body.hex()}"
        n = body[0]
        if expect[2] is not None:
            assert list(struct.unpack(f">{n // 2}H", body[1:1 + n])) == expect[2], f"{where}: read data"


# ---- TCP ---------------------------------------------------------------------------------------
def _mbap(tid: int, unit: int, pdu: bytes, length: int | None = None, pid: int = 0) -> bytes:
    return struct.pack(">HHHB", tid, pid, len(pdu) + 1 if length is None else length, unit) + pdu


class _TcpStream:
    """Pipelined clean frames on one connection; answers matched by transaction id."""

    def __init__(self, port: int):
        self.sock = socket.create_connection(("127.0.0.1", port))
        self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.buf = b""
        self.waiting: dict[int, tuple] = {}     # tid -> (frame, unit)
        self.answered = 0

    def send(self, frames: list[bytes]):
        self.sock.sendall(b"".join(frames))

    def collect(self, timeout: float = 5.0):
        """Read answers until every frame that must be answered has been."""
        deadline = time.monotonic() + timeout
        while any(f.expect[0] in (EXC, OK) for f, _ in self.waiting.values()):
            left = deadline - time.monotonic()
            missing = [(t, f.kind, f.pdu.hex()) for t, (f, _) in self.waiting.items() if f.expect[0] in (EXC, OK)]
            assert left > 0, f"no answer to {len(missing)} well-formed frames, e.g. {missing[:3]}"
            r, _, _ = select.select([self.sock], [], [], left)
            if r:
                data = self.sock.recv(65536)
                assert data, "the rig closed the connection"
                self.buf += data
                self._parse()
        self.waiting = {t: v for t, v in self.waiting.items() if v[0].expect[0] != NONE}

    def _parse(self):
        while len(self.buf) >= 8:
            tid, pid, length, unit = struct.unpack(">HHHB", self.buf[:7])
            if len(self.buf) < 6 + length:
                return
            pdu, self.buf = self.buf[7:6 + length], self.buf[6 + length:]
            assert pid == 0
            assert tid in self.waiting, f"answer to an unknown transaction {tid}: {pdu.hex()}"
            frame, sent_unit = self.waiting.pop(tid)
            assert unit == sent_unit, f"answer for unit {unit} to a request for unit {sent_unit}"
            assert frame.expect[0] != NONE, f"answer to a frame without a function code: {pdu.hex()}"
            _expect_ok(frame.expect, pdu[0], pdu[1:], f"{frame.kind} {frame.pdu.hex()}")
            self.answered += 1


def test_fuzz_tcp(rig_process):
    rig = rig_process("--rig", "flutter", "--lockstep")
    sheet = Datasheet("flutter")
    checker = Checker(rig.url, "flutter", sheet)
    fuzz = Fuzzer("flutter", sheet, SEED)
    rng = fuzz.rng
    stream = _TcpStream(rig.port)
    counts: dict[str, int] = {}
    tid = 0
    pipeline: list[bytes] = []
    sent = 0
    try:
        while sent < N_FRAMES:
            f = fuzz.next()
            unit = 1 if rng.random() < 0.85 else int(rng.integers(256))
            tid = tid % 0xFFFF + 1
            if rng.random() < 0.75 or not fuzz.safe(f.pdu):
                # clean: a well-delimited MBAP frame, pipelined, its answer checked
                stream.waiting[tid] = (f, unit)
                pipeline.append(_mbap(tid, unit, f.pdu))
                counts[f.kind] = counts.get(f.kind, 0) + 1
                if len(pipeline) >= 25:
                    stream.send(pipeline)
                    pipeline = []
                    stream.collect()
            else:
                # dirty: break the TCP stream framing on a throwaway connection
                frame = _mbap(tid, unit, f.pdu)
                k = int(rng.integers(6))
                if k == 0:
                    raw, name = frame[:int(rng.integers(1, len(frame)))], "tcp_truncated"
                elif k == 1:
                    raw, name = frame + bytes(rng.integers(0, 256, int(rng.integers(1, 40)), dtype=np.uint8)), \
                        "tcp_overlong"
                elif k == 2:
                    raw, name = _mbap(tid, unit, f.pdu, length=int(rng.integers(0, 0x10000))), "tcp_bad_length"
                elif k == 3:
                    raw, name = _mbap(tid, unit, f.pdu, pid=int(rng.integers(1, 0x10000))), "tcp_bad_protocol"
                elif k == 4:
                    raw, name = bytes(rng.integers(0, 256, int(rng.integers(1, 300)), dtype=np.uint8)), "tcp_random"
                else:
                    raw, name = _mbap(tid, unit, f.pdu[:int(rng.integers(0, 2))]), "tcp_no_function"
                counts[name] = counts.get(name, 0) + 1
                # alone on its own connection, closed at once: on a TCP stream the bytes
                # that follow a cut frame would complete it, and a frame completed by
                # whatever comes next is, to the device, simply a frame
                with socket.create_connection(("127.0.0.1", rig.port)) as dirty:
                    dirty.sendall(raw)
            sent += 1
            if sent % CHECK_EVERY == 0:
                stream.send(pipeline)
                pipeline = []
                stream.collect()
                checker.check(f"after {sent} frames")
        stream.send(pipeline)
        stream.collect()
        time.sleep(0.2)
        checker.check("at the end")
        assert rig.proc.poll() is None, "the rig process died"
    finally:
        checker.close()
        stream.sock.close()
    print(f"\nTCP: {sent} frames, {stream.answered} answers checked, {checker.checks} client checks, "
          f"{fuzz.vetoed} valid writes vetoed; by kind {dict(sorted(counts.items()))}")
    assert sent >= N_FRAMES
    assert stream.answered > 0.5 * sent
    for kind in Fuzzer.KINDS + ["tcp_truncated", "tcp_overlong", "tcp_bad_length", "tcp_bad_protocol",
                                "tcp_random", "tcp_no_function"]:
        assert counts.get(kind, 0) >= 20, kind


# ---- RTU ---------------------------------------------------------------------------------------
def rtu_size(frame: bytes) -> int | None:
    """The length of an RTU request frame as the device frames it (None: other)."""
    if len(frame) < 2:
        return None
    fc = frame[1]
    if fc & 0x80:
        return 5
    if fc in (3, 4, 6):
        return 8
    if fc == 22:
        return 10
    if fc == 16 and len(frame) >= 7:
        return frame[6] + 9
    if fc == 23 and len(frame) >= 11:
        return frame[10] + 13
    return None


def rtu_answer_size(buf: bytes) -> int | None:
    if len(buf) < 3:
        return None
    fc = buf[1]
    if fc & 0x80:
        return 5
    if fc in (3, 4, 23):
        return 5 + buf[2]
    if fc in (6, 16):
        return 8
    if fc == 22:
        return 10
    return None


class _Line:
    """The master's end of the cable, raw. Each frame goes to a different unit
    address (the device answers every unit and echoes it), so a late answer to an
    earlier frame is recognised and set aside rather than taken for this one's."""

    def __init__(self, path: str):
        self.fd = os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        tty.setraw(self.fd)
        self.stale = 0

    def drain(self):
        while select.select([self.fd], [], [], 0)[0]:
            self.stale += len(os.read(self.fd, 4096))

    def send(self, data: bytes):
        """Write all of data (the pty's buffer fills when the far end is slow to read)."""
        view, deadline = memoryview(data), time.monotonic() + 10
        while view:
            try:
                view = view[os.write(self.fd, view):]
            except BlockingIOError:
                assert time.monotonic() < deadline, "the device has stopped reading the line"
                select.select([], [self.fd], [], 0.1)

    def exchange(self, frame: bytes, unit: int, want_answer: bool) -> bytes:
        """Send; return the answer from `unit`, or b"" after the line has been quiet
        (RTU_QUIET_S; up to 1 s for the first byte of an answer we expect)."""
        self.drain()
        self.send(frame)
        got = b""
        deadline = time.monotonic() + 1.0
        while True:
            size = rtu_answer_size(got)
            if size is not None and len(got) >= size:
                answer, got = got[:size], got[size:]
                if answer[0] == unit:
                    return answer
                self.stale += size               # a late answer to an earlier frame
                continue
            if got and got[0] != unit and size is None and len(got) >= 3:
                self.stale += len(got)           # something unparseable from an earlier frame
                got = b""
            wait = deadline - time.monotonic() if (want_answer and not got) else RTU_QUIET_S
            if wait <= 0 or not select.select([self.fd], [], [], wait)[0]:
                return got if got and got[0] == unit else b""
            got += os.read(self.fd, 4096)

    def close(self):
        os.close(self.fd)


def test_fuzz_rtu(rig_process, pty_pair):
    rig = rig_process("--rig", "oscillator", "--lockstep", "--no-tcp", "--serial", pty_pair.b)
    _run_rtu(rig, pty_pair)


def _run_rtu(rig, cable):
    sheet = Datasheet("oscillator")
    checker = Checker(f"serial://{cable.a}", "oscillator", sheet)
    fuzz = Fuzzer("oscillator", sheet, SEED + 1)
    rng = fuzz.rng
    line = _Line(cable.a)
    kinds: dict[str, int] = {}
    mutations: dict[str, int] = {}
    answered = relaxed = resyncs = noise = retried = 0
    # whether the device may hold an incomplete frame (the tail of a mutated one):
    # then the next frame can be taken as its continuation and go unanswered
    dirty = False
    history: collections.deque = collections.deque(maxlen=3)
    sent = 0
    try:
        while sent < N_FRAMES:
            f = fuzz.next()
            unit = 1 + sent % 247
            body = bytes([unit]) + f.pdu
            frame = body + crc16(body)
            size = rtu_size(frame)
            if size is not None and 4 <= size < len(frame) and frame[size - 2:size] == \
                    crc16(frame[:size - 2]) and sheet.classify(frame[1:size - 2])[0]:
                # RTU frames a write by its byte count: bytes past it that happen to be
                # the CRC of the shorter frame (1 in 256 for one appended byte, by the
                # CRC's algebra) make it a valid write, which a fuzz frame must not be
                fuzz.vetoed += 1
                continue
            clean = size == len(frame) and f.expect[0] in (EXC, OK)
            expect = f.expect if clean else (ANY,)
            name = "as_is" if clean else "inconsistent_length"
            k, pause = rng.random(), rng.random()     # drawn every frame: the sequence does not depend on timing
            if k < 0.10 and clean:              # CRC corrupted: the device must ignore it
                i = len(frame) - 1 - int(rng.integers(2))
                frame = frame[:i] + bytes([frame[i] ^ int(rng.integers(1, 256))]) + frame[i + 1:]
                name, expect = "bad_crc", (NONE,)
            elif 0.10 <= k < 0.17 and fuzz.safe(f.pdu):
                frame, name, expect = frame[:int(rng.integers(1, len(frame)))], "truncated", (NONE,)
            elif 0.17 <= k < 0.22 and fuzz.safe(f.pdu):
                frame += bytes(rng.integers(0, 256, int(rng.integers(1, 20)), dtype=np.uint8))
                name, expect = "overlong", (ANY,)
            elif 0.22 <= k < 0.27 and fuzz.safe(f.pdu):
                frame = bytearray(frame)
                for _ in range(int(rng.integers(1, 4))):
                    i = int(rng.integers(len(frame)))
                    frame[i] ^= 1 << int(rng.integers(8))
                frame, name, expect = bytes(frame), "garbled", (ANY,)
            elif 0.27 <= k < 0.31:
                frame = bytes(rng.integers(0, 256, int(rng.integers(1, 120)), dtype=np.uint8))
                name, expect = "random_bytes", (ANY,)
            kinds[f.kind] = kinds.get(f.kind, 0) + 1
            mutations[name] = mutations.get(name, 0) + 1
            want = expect[0] in (EXC, OK) and not dirty
            got = line.exchange(frame, unit, want)
            if want and not got:
                # the device should have answered. On a loaded host its process may
                # not have run during the silence that was to separate line noise from
                # this frame (a pty keeps no timing), so both arrived in one read:
                # one more silence and the same frame (invalid writes and reads are
                # idempotent), which must then be answered
                time.sleep(RTU_SILENCE_S)
                got = line.exchange(frame, unit, True)
                retried += 1
            where = f"frame {sent} ({f.kind}, {name}) {frame.hex()} -> {got.hex()}; before: {list(history)}"
            history.append(f"{name} {frame.hex()} -> {got.hex()}")
            if expect[0] == NONE and not dirty:
                assert not got, f"answer to a frame the device must ignore: {where}"
            if got and expect[0] in (EXC, OK):
                size = rtu_answer_size(got)
                assert size is not None and len(got) == size, f"malformed answer: {where}"
                assert got[-2:] == crc16(got[:-2]), f"answer with a bad CRC: {where}"
                _expect_ok(expect, got[1], got[2:-2], where)
                answered += 1
            elif expect[0] in (EXC, OK):
                assert dirty, f"no answer, twice: {where}"
                relaxed += 1
            if got:
                dirty = False           # the device framed something: its buffer is empty
            else:
                # no answer: the device may hold a partial frame, or may not have read
                # this one yet (a pty has no inter-frame gap: read together with the
                # next frame, a bad CRC makes pymodbus drop both)
                dirty = True
                if pause < 0.01:                        # now and then the bus falls silent:
                    time.sleep(RTU_SILENCE_S)           # the device must drop the partial frame
                    dirty = False
                    resyncs += 1
                else:
                    # line noise: 0xFF bytes, longer than any frame. Whatever the device
                    # holds is completed with them and fails its CRC; and a partial frame
                    # is never completed by the next *frame*, whose bytes (unlike 0xFFFF,
                    # a NaN or out of range in every register a fuzz frame targets)
                    # could, after a chance CRC match, make a valid write
                    line.exchange(NOISE, unit=-1, want_answer=False)
                    noise += 1
            sent += 1
            if sent % CHECK_EVERY == 0:
                time.sleep(RTU_SILENCE_S)               # inter-frame silence: the device resynchronises
                line.drain()
                checker.check(f"after {sent} frames")
                dirty = False
        time.sleep(RTU_SILENCE_S)
        line.drain()
        checker.check("at the end")
        assert rig.proc.poll() is None, "the rig process died"
    finally:
        line.close()
        checker.close()
    print(f"\nRTU: {sent} frames, {answered} answers checked ({relaxed} relaxed after a partial frame, "
          f"{resyncs} silences, {noise} noise bursts, {retried} frames resent), {checker.checks} client checks, {fuzz.vetoed} valid writes vetoed, "
          f"{line.stale} late bytes; generator {dict(sorted(kinds.items()))}; "
          f"on the line {dict(sorted(mutations.items()))}")
    # the storm must have exercised the answer path (how many answers a partial
    # frame swallows depends on when the device reads the pty: loose bounds)
    assert answered > 0.3 * sent
    assert relaxed < 0.2 * sent
    assert retried < 0.02 * sent
    for kind in Fuzzer.KINDS:
        assert kinds.get(kind, 0) >= 50, kind
    for name in ("as_is", "bad_crc", "truncated", "overlong", "garbled", "random_bytes"):
        assert mutations.get(name, 0) >= 200, name
