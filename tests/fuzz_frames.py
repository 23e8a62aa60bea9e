"""The fuzz frames and the datasheet as a model (used by tests/rig_fuzzing.py).

A seeded generator (`Fuzzer`) of Modbus PDUs designed to be invalid: random bytes;
mutated function codes, addresses, counts and byte counts; bit flips; writes to
every holding register with NaN, infinities, out-of-range and random garbage
values, partial float writes, writes to unmapped addresses and multi-register
writes in which one value is bad. `Datasheet.classify` says what the register map
makes of each PDU: whether it would change a setting (then it is never sent) and
which answer it must get.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass

import numpy as np

from rig_sim.device import register_map as M


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
        if fc in KNOWN_FC:
            return False, (ANY,)            # coils, diagnostics, identification...: no setting
        return False, (EXC, 1)              # unknown function, 0x80..0xFF included


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
