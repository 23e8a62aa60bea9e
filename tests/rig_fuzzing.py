"""Robustness: the service under a storm of random and mutated Modbus frames (the
runners shared by tests/test_rig_fuzz.py and benchmarks/fuzz_benchmark.py).

N frames over Modbus TCP (flutter rig) and over Modbus RTU through a socat pty
pair (oscillator rig), from the seeded generator of tests/fuzz_frames.py, with
the transport's own mutations (broken MBAP framing; bad CRCs, truncated, over-long
and garbled RTU frames, line noise) and unit ids. Every frame is checked against
the model of the datasheet (`Datasheet`) before it is sent: frames that the
datasheet says would legitimately change something (a valid in-range write) are
not sent, so that **no setting may change** during the storm.

Throughout, a real client (`RigClient`, pymodbus) interleaves valid requests:
it reads the identification, every holding register (compared with the snapshot
taken before the storm) and the status/counter block, writes a setting, reads it
back and restores it. Each well-formed frame's own answer is also checked: the
exception code the datasheet prescribes (02 unmapped or partial value, 03 out of
range or inconsistent counts, 01 undecodable), holding-register reads returning
the snapshot words, and on RTU no answer at all to a frame with a bad CRC. At
the end the rig process must still be running.

The rigs run in --lockstep so that nothing but a write could change a setting.

Unit ids (docs/protocol.md). The rig is unit 1. Over TCP, frames to 1, 0 and 255
are the device's own; every other id must get exception 0B and change nothing. Over
RTU, 85 % of the frames go to unit 1; the rest go to other units or are broadcasts,
which the device must never answer (a broadcast write that would be valid is vetoed
like any valid write). An answer is taken as this frame's only if it carries the
frame's unit and function code; anything else is a late answer to an earlier frame.

RTU timing. A pty has no inter-frame gaps, and pymodbus's RTU framer drops its
whole buffer on a CRC failure, so frames must not run together. Each fuzz frame
goes out as soon as the previous answer is in or, for a frame that gets none,
after 1 ms of line quiet (10 ms for a frame the device may answer or not); such a frame is followed by a burst of line noise
(270 x 0xFF, longer than any frame: whatever partial frame the device holds is
completed with it and fails its CRC — never completed by the next real frame,
which after a chance CRC match could make a valid write) or, now and then, by
40 ms of silence, after which the device must have dropped any partial frame
(server.RTU_FRAME_SILENCE_S = 20 ms, the inter-frame silence rule of the Modbus
serial-line spec) and must answer the next frame. A frame sent while the device
may still hold something unanswered may go unanswered (counted as "relaxed").
A frame the device should have answered but did not is sent once more after
another silence (on a loaded host the device's process may not run during a
silence, and a pty keeps no timing) and must then be answered; so is a frame
whose answer does not match while earlier frames went unanswered (theirs may come
late). A frame the device must ignore that gets an answer while earlier frames went
unanswered is sent once more after a silence too (the answer may be the frame
before's, late, when that frame took an earlier answer of the same kind for its own),
and must then get none. Before every interleaved client check the line is silent for
40 ms.
"""

from __future__ import annotations

import collections
import os
import select
import socket
import struct
import threading
import time
import tty
from pathlib import Path

import numpy as np

from cbc_controller.client import RigClient
from rig_sim.device import register_map as M
from tests.fuzz_frames import ANY, EXC, NONE, OK, Datasheet, Frame, Fuzzer, crc16

SEED = 20240607
CHECK_EVERY = 200           # fuzz frames between interleaved client checks
RTU_SILENCE_S = 0.04        # line silence before a client check (device discards partials after 20 ms)
RTU_QUIET_S = 0.001         # line quiet that ends the wait for an unanswered frame
NOISE = b"\xff" * 270       # RTU line noise: longer than the longest frame (256 bytes)

MODEL = {"flutter": "VCL-FLUTTER-2DOF", "oscillator": "VCL-EDOSC-1DOF"}


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


def count_exception(codes: collections.Counter, fc: int, body: bytes) -> None:
    if fc & 0x80 and body:
        codes[f"{body[0]:02X}"] += 1


def _expect_ok(expect, fc, body, where, request_fc):
    """Check one answer (function code + data) against the expectation."""
    if expect[0] == EXC:
        assert fc == request_fc | 0x80, f"{where}: expected exception {expect[1]} to function " \
            f"{request_fc:#04x}, got function {fc:#04x} {body.hex()}"
        assert body[:1] == bytes([expect[1]]), f"{where}: expected exception {expect[1]}, got {body.hex()}"
    elif expect[0] == OK:
        assert fc == expect[1], f"{where}: expected a normal answer to {expect[1]}, got {fc} {body.hex()}"
        n = body[0]
        if expect[2] is not None:
            assert list(struct.unpack(f">{n // 2}H", body[1:1 + n])) == expect[2], f"{where}: read data"


# ---- measurements ------------------------------------------------------------------------------
RIG_UNIT = 1                     # the rigs run with the default --unit
TCP_THIS_DEVICE = (RIG_UNIT, 0, 255)
GATEWAY_TARGET_FAILED = 0x0B
STATUS_READ = struct.pack(">BHH", 4, M.BY_NAME["status"].address, 1)     # FC4: the status word


def rss_kib(pid: int) -> int:
    """Resident memory of a process, KiB (VmRSS)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    raise RuntimeError(f"no VmRSS for process {pid}")


def latency_ms(lat_s: list[float]) -> dict:
    if not lat_s:
        return {"n": 0}
    ms = np.asarray(lat_s) * 1e3
    return {"n": len(ms), "p50_ms": round(float(np.percentile(ms, 50)), 3),
            "p99_ms": round(float(np.percentile(ms, 99)), 3), "max_ms": round(float(ms.max()), 3)}


def _answer_matches(expect, got: bytes, request_fc: int) -> bool:
    try:
        _expect_ok(expect, got[1], got[2:-2], "", request_fc)
    except AssertionError:
        return False
    return True


# ---- TCP ---------------------------------------------------------------------------------------
def _mbap(tid: int, unit: int, pdu: bytes, length: int | None = None, pid: int = 0) -> bytes:
    return struct.pack(">HHHB", tid, pid, len(pdu) + 1 if length is None else length, unit) + pdu


def tcp_expectation(frame: Frame, unit: int) -> tuple:
    """docs/protocol.md: units 1 (the rig's), 0 and 255 are the device itself; any
    other unit id gets 0B (gateway target failed to respond) whatever the PDU."""
    return frame.expect if unit in TCP_THIS_DEVICE else (EXC, GATEWAY_TARGET_FAILED)


class _TcpStream:
    """Pipelined clean frames on one connection; answers matched by transaction id."""

    def __init__(self, port: int, codes: collections.Counter):
        self.sock = socket.create_connection(("127.0.0.1", port))
        self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.buf = b""
        self.waiting: dict[int, tuple] = {}     # tid -> (frame, unit, expectation)
        self.answered = 0
        self.codes = codes

    def send(self, frames: list[bytes]):
        self.sock.sendall(b"".join(frames))

    def collect(self, timeout: float = 5.0):
        """Read answers until every frame that must be answered has been."""
        deadline = time.monotonic() + timeout
        while any(e[0] in (EXC, OK) for _, _, e in self.waiting.values()):
            left = deadline - time.monotonic()
            missing = [(t, f.kind, f.pdu.hex()) for t, (f, _, e) in self.waiting.items() if e[0] in (EXC, OK)]
            assert left > 0, f"no answer to {len(missing)} well-formed frames, e.g. {missing[:3]}"
            r, _, _ = select.select([self.sock], [], [], left)
            if r:
                data = self.sock.recv(65536)
                assert data, "the rig closed the connection"
                self.buf += data
                self._parse()
        self.waiting = {t: v for t, v in self.waiting.items() if v[2][0] != NONE}

    def _parse(self):
        while len(self.buf) >= 8:
            tid, pid, length, unit = struct.unpack(">HHHB", self.buf[:7])
            if len(self.buf) < 6 + length:
                return
            pdu, self.buf = self.buf[7:6 + length], self.buf[6 + length:]
            assert pid == 0
            assert tid in self.waiting, f"answer to an unknown transaction {tid}: {pdu.hex()}"
            frame, sent_unit, expect = self.waiting.pop(tid)
            assert unit == sent_unit, f"answer for unit {unit} to a request for unit {sent_unit}"
            assert expect[0] != NONE, f"answer to a frame without a function code: {pdu.hex()}"
            count_exception(self.codes, pdu[0], pdu[1:])
            _expect_ok(expect, pdu[0], pdu[1:], f"{frame.kind} unit {unit} {frame.pdu.hex()}", frame.pdu[0])
            self.answered += 1


class _TcpProbe(threading.Thread):
    """A well-behaved second master on its own connection, timing FC4 reads of the
    status word while the storm runs: the latency a real client sees."""

    def __init__(self, port: int, pause_s: float = 0.002):
        super().__init__(name="fuzz-probe", daemon=True)
        self.sock = socket.create_connection(("127.0.0.1", port))
        self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.pause_s = pause_s
        self.stop_event = threading.Event()
        self.lat: list[float] = []
        self.error: BaseException | None = None
        self.tid = 0

    def read_once(self) -> float:
        self.tid = self.tid % 0xFFFF + 1
        t0 = time.perf_counter()
        self.sock.sendall(_mbap(self.tid, RIG_UNIT, STATUS_READ))
        got = b""
        while len(got) < 11:
            chunk = self.sock.recv(64)
            assert chunk, "the rig closed the probe's connection"
            got += chunk
        dt = time.perf_counter() - t0
        assert struct.unpack(">H", got[:2])[0] == self.tid and got[7:9] == b"\x04\x02", got.hex()
        return dt

    def run(self):
        try:
            while not self.stop_event.is_set():
                self.lat.append(self.read_once())
                self.stop_event.wait(self.pause_s)
        except BaseException as exc:  # reported by finish()
            self.error = exc

    def finish(self, n_after: int) -> tuple[list[float], list[float]]:
        """Stop; (latencies during the storm, n_after latencies once it is over)."""
        self.stop_event.set()
        self.join(timeout=10)
        if self.error is not None:
            raise self.error
        after = [self.read_once() for _ in range(n_after)]
        self.sock.close()
        return self.lat, after


def run_tcp(rig, n_frames: int, seed: int = SEED, n_after: int = 1000) -> dict:
    """The storm over TCP against a `--lockstep` flutter rig; asserts as it goes
    (answers, settings unchanged, the rig alive) and returns what it saw."""
    sheet = Datasheet("flutter")
    checker = Checker(rig.url, "flutter", sheet)
    fuzz = Fuzzer("flutter", sheet, seed)
    rng = fuzz.rng
    codes: collections.Counter = collections.Counter()
    stream = _TcpStream(rig.port, codes)
    rss_before = rss_kib(rig.proc.pid)
    probe = _TcpProbe(rig.port)
    probe.start()
    counts: collections.Counter = collections.Counter()
    tid = 0
    pipeline: list[bytes] = []
    sent = 0
    t0 = time.perf_counter()
    try:
        while sent < n_frames:
            f = fuzz.next()
            unit = RIG_UNIT if rng.random() < 0.85 else int(rng.integers(256))
            tid = tid % 0xFFFF + 1
            if rng.random() < 0.75 or not fuzz.safe(f.pdu):
                # clean: a well-delimited MBAP frame, pipelined, its answer checked
                stream.waiting[tid] = (f, unit, tcp_expectation(f, unit))
                pipeline.append(_mbap(tid, unit, f.pdu))
                counts[f.kind] += 1
                counts["unit_this_device" if unit in TCP_THIS_DEVICE else "unit_other"] += 1
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
                counts[name] += 1
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
        storm_s = time.perf_counter() - t0
        during, after = probe.finish(n_after)
        time.sleep(0.2)
        checker.check("at the end")
        assert rig.proc.poll() is None, "the rig process died"
        rss_after = rss_kib(rig.proc.pid)
    finally:
        probe.stop_event.set()
        checker.close()
        stream.sock.close()
    return {"transport": "tcp", "rig": "flutter --lockstep", "seed": seed, "frames": sent,
            "storm_s": round(storm_s, 1), "answers_checked": stream.answered,
            "client_checks": checker.checks, "holding_registers_compared": len(checker.holding0),
            "settings_unchanged": True, "answers_after": True, "valid_writes_vetoed": fuzz.vetoed,
            "rss_kib": {"before": rss_before, "after": rss_after},
            "exception_codes": dict(sorted(codes.items())),
            "latency_status_read": {"during": latency_ms(during), "after": latency_ms(after)},
            "by_kind": dict(sorted(counts.items()))}


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
    """The master's end of the cable, raw. An answer is this frame's only if it
    carries the frame's unit and function code (exception bit aside); anything else
    is a late answer to an earlier frame, counted and set aside."""

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

    @staticmethod
    def _ours(buf: bytes, unit: int, fc: int) -> bool:
        return len(buf) >= 2 and buf[0] == unit and buf[1] | 0x80 == fc | 0x80

    def exchange(self, frame: bytes, want_answer: bool, quiet_s: float = RTU_QUIET_S) -> bytes:
        """Send; return the answer to this frame, or b"" after the line has been
        quiet for quiet_s (up to 1 s for the first byte of an answer we expect)."""
        unit, fc = (frame[0], frame[1]) if len(frame) >= 2 else (-1, -1)
        self.drain()
        self.send(frame)
        got = b""
        deadline = time.monotonic() + 1.0
        while True:
            size = rtu_answer_size(got)
            if size is not None and len(got) >= size:
                answer, got = got[:size], got[size:]
                if self._ours(answer, unit, fc):
                    return answer
                self.stale += size               # a late answer to an earlier frame
                continue
            if len(got) >= 3 and size is None and not self._ours(got, unit, fc):
                self.stale += len(got)           # something unparseable from an earlier frame
                got = b""
            wait = deadline - time.monotonic() if (want_answer and not got) else quiet_s
            if wait <= 0 or not select.select([self.fd], [], [], wait)[0]:
                return got if self._ours(got, unit, fc) else b""
            got += os.read(self.fd, 4096)

    def timed_reads(self, n: int) -> list[float]:
        """n FC4 reads of the status word from the rig's unit; their round trips."""
        body = bytes([RIG_UNIT]) + STATUS_READ
        frame = body + crc16(body)
        out = []
        for _ in range(n):
            t0 = time.perf_counter()
            got = self.exchange(frame, want_answer=True)
            out.append(time.perf_counter() - t0)
            assert got[:3] == bytes([RIG_UNIT, 4, 2]) and got[-2:] == crc16(got[:-2]), got.hex()
        return out

    def close(self):
        os.close(self.fd)


def _device_sees_a_valid_write(sheet: Datasheet, frame: bytes) -> bool:
    """Whether the device, sizing the frame by its function code, finds a CRC-valid
    frame that would change a setting. A frame longer than its own size (a payload
    longer than its byte count, say) puts two arbitrary bytes where the device looks
    for the CRC: one in 65,536 of them matches."""
    size = rtu_size(frame)
    if size is None or size > len(frame) or frame[0] not in (RIG_UNIT, 0):
        return False
    return crc16(frame[:size - 2]) == frame[size - 2:size] and sheet.classify(frame[1:size - 2])[0]


def run_rtu(rig, cable, n_frames: int, seed: int = SEED + 1, n_after: int = 300) -> dict:
    """The storm over RTU against a `--lockstep` oscillator rig on `cable.b`."""
    sheet = Datasheet("oscillator")
    checker = Checker(f"serial://{cable.a}", "oscillator", sheet)
    fuzz = Fuzzer("oscillator", sheet, seed)
    rng = fuzz.rng
    line = _Line(cable.a)
    rss_before = rss_kib(rig.proc.pid)
    kinds: collections.Counter = collections.Counter()
    mutations: collections.Counter = collections.Counter()
    codes: collections.Counter = collections.Counter()
    during: list[float] = []
    answered = relaxed = resyncs = noise = retried = resynced_mismatch = 0
    # frames that went unanswered since the line was last silent: an answer to one of
    # them may still come, and (one unit, and often the same function code) be taken
    # for a later frame's
    unanswered = 0
    # whether the device may hold an incomplete frame (the tail of a mutated one):
    # then the next frame can be taken as its continuation and go unanswered
    dirty = False
    history: collections.deque = collections.deque(maxlen=3)
    sent = 0
    t0 = time.perf_counter()
    try:
        while sent < n_frames:
            f = fuzz.next()
            r = rng.random()
            unit = RIG_UNIT if r < 0.85 else 0 if r < 0.90 else int(rng.integers(2, 256))
            body = bytes([unit]) + f.pdu
            frame = body + crc16(body)
            clean = rtu_size(frame) == len(frame) and f.expect[0] in (EXC, OK)
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
            if unit != RIG_UNIT and name in ("as_is", "inconsistent_length"):
                # another slave's frame, or a broadcast: the device must stay silent
                name, expect = ("broadcast" if unit == 0 else "other_unit"), (NONE,)
            if _device_sees_a_valid_write(sheet, frame):
                fuzz.vetoed += 1                # by chance: see _device_sees_a_valid_write
                continue
            kinds[f.kind] += 1
            mutations[name] += 1
            want = expect[0] in (EXC, OK) and not dirty
            # a frame the device may answer or not: a longer quiet, so that its
            # answer is not left on the line for the next frame
            quiet = 10 * RTU_QUIET_S if expect[0] == ANY else RTU_QUIET_S
            t_send = time.perf_counter()
            got = line.exchange(frame, want, quiet)
            if want and got:
                during.append(time.perf_counter() - t_send)
            if got and unanswered and expect[0] in (EXC, OK) and not _answer_matches(expect, got, frame[1]):
                # perhaps a late answer to an earlier unanswered frame: silence (every
                # late answer arrives and is drained), then the same frame once more
                time.sleep(RTU_SILENCE_S)
                line.drain()
                got = line.exchange(frame, True)
                unanswered = 0
                resynced_mismatch += 1
            if got and unanswered and expect[0] == NONE and not dirty:
                # an answer to a frame the device must ignore, while earlier frames went
                # unanswered: perhaps the answer to the frame before, late (that frame
                # took an earlier one's late answer, of the same unit and function code,
                # for its own). Silence, then the same frame once more: the device must
                # now stay silent, so a device that answers it is still caught
                time.sleep(RTU_SILENCE_S)
                line.drain()
                got = line.exchange(frame, False)
                unanswered = 0
                resynced_mismatch += 1
            if want and not got:
                # the device should have answered. On a loaded host its process may
                # not have run during the silence that was to separate line noise from
                # this frame (a pty keeps no timing), so both arrived in one read:
                # one more silence and the same frame (invalid writes and reads are
                # idempotent), which must then be answered
                time.sleep(RTU_SILENCE_S)
                got = line.exchange(frame, True)
                unanswered = 0
                retried += 1
            where = f"frame {sent} ({f.kind}, {name}) {frame.hex()} -> {got.hex()}; before: {list(history)}"
            history.append(f"{name} {frame.hex()} -> {got.hex()}")
            if expect[0] == NONE and not dirty:
                assert not got, f"answer to a frame the device must ignore: {where}"
            if got:
                count_exception(codes, got[1], got[2:-2])
            if got and expect[0] in (EXC, OK):
                size = rtu_answer_size(got)
                assert size is not None and len(got) == size, f"malformed answer: {where}"
                assert got[-2:] == crc16(got[:-2]), f"answer with a bad CRC: {where}"
                _expect_ok(expect, got[1], got[2:-2], where, frame[1])
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
                unanswered += 1
                if pause < 0.01:                        # now and then the bus falls silent:
                    time.sleep(RTU_SILENCE_S)           # the device must drop the partial frame
                    dirty = False
                    unanswered = 0
                    resyncs += 1
                else:
                    # line noise: 0xFF bytes, longer than any frame. Whatever the device
                    # holds is completed with them and fails its CRC; and a partial frame
                    # is never completed by the next *frame*, whose bytes (unlike 0xFFFF,
                    # a NaN or out of range in every register a fuzz frame targets)
                    # could, after a chance CRC match, make a valid write
                    line.exchange(NOISE, want_answer=False)
                    noise += 1
            sent += 1
            if sent % CHECK_EVERY == 0:
                time.sleep(RTU_SILENCE_S)               # inter-frame silence: the device resynchronises
                line.drain()
                checker.check(f"after {sent} frames")
                dirty = False
                unanswered = 0
        storm_s = time.perf_counter() - t0
        time.sleep(RTU_SILENCE_S)
        line.drain()
        checker.check("at the end")
        time.sleep(RTU_SILENCE_S)
        after = line.timed_reads(n_after)
        assert rig.proc.poll() is None, "the rig process died"
        rss_after = rss_kib(rig.proc.pid)
    finally:
        line.close()
        checker.close()
    return {"transport": "rtu (socat pty, 115200 Bd)", "rig": "oscillator --lockstep", "seed": seed,
            "frames": sent, "storm_s": round(storm_s, 1), "answers_checked": answered,
            "relaxed_after_partial_frame": relaxed, "silences": resyncs, "noise_bursts": noise,
            "frames_resent": retried, "frames_resent_after_a_mismatch": resynced_mismatch, "late_bytes": line.stale,
            "client_checks": checker.checks, "holding_registers_compared": len(checker.holding0),
            "settings_unchanged": True, "answers_after": True, "valid_writes_vetoed": fuzz.vetoed,
            "rss_kib": {"before": rss_before, "after": rss_after},
            "exception_codes": dict(sorted(codes.items())),
            "latency_answered_frame": {"during": latency_ms(during), "after": latency_ms(after)},
            "by_kind": dict(sorted(kinds.items())), "on_the_line": dict(sorted(mutations.items()))}
