"""A third-party Modbus master (mbpoll, libmodbus) drives the running service.

Over Modbus TCP and over Modbus RTU through a socat pty pair (the rig on one
end, mbpoll on the other), mbpoll reads the identification block, watches the
measurements move in real time, writes a setting and reads the exact float32
words back, and gets the datasheet's exceptions for out-of-range values and
unmapped addresses, after which the setting is as it was.

mbpoll reference numbers are 1-based: register address A is `-r A+1`. Expected
values come from the datasheet (rig_sim/device/register_map.py) and the rig
specifications (model strings, loop rates), and float32 words are computed here
with `struct`, independently of the rig's own codec.
"""

from __future__ import annotations

import math
import re
import shutil
import struct
import subprocess
import time
from pathlib import Path

import pytest

from rig_sim.device import register_map as M
from rig_sim.harness import PtyPair, RigProcess

REPO = Path(__file__).resolve().parents[1]
MBPOLL = shutil.which("mbpoll")
SOCAT = shutil.which("socat")

pytestmark = pytest.mark.skipif(MBPOLL is None, reason="mbpoll is not installed (apt-get install mbpoll; .ci/run does)")

# one result line of mbpoll: "[13]: \t12.5" (reference, value)
_RESULT = re.compile(r"^\[(\d+)\]:\s+(\S+)\s*$", re.M)


def f32_words(value: float) -> list[int]:
    """float32, big-endian word order (ABCD), as the datasheet specifies."""
    return list(struct.unpack(">HH", struct.pack(">f", value)))


class Mbpoll:
    """mbpoll aimed at one rig endpoint; every call is one mbpoll process (`-1`)."""

    def __init__(self, transport: str, rig: RigProcess, pty: str | None = None):
        self.transport, self.rig = transport, rig
        if transport == "tcp":
            port = rig.endpoints[0].rsplit(":", 1)[1]
            self.link, self.target = ["-m", "tcp", "-p", port], "127.0.0.1"
        else:
            self.link, self.target = ["-m", "rtu", "-b", "115200", "-P", "none"], pty

    def run(self, *options: str, values: tuple = ()) -> subprocess.CompletedProcess:
        cmd = [MBPOLL, *self.link, "-a", "1", "-o", "3", "-1", *options, self.target, *map(str, values)]
        return subprocess.run(cmd, capture_output=True, text=True, timeout=30)

    @staticmethod
    def results(proc: subprocess.CompletedProcess) -> dict[int, str]:
        return {int(ref): text for ref, text in _RESULT.findall(proc.stdout)}

    # reads ------------------------------------------------------------------------------------
    def words(self, table: str, address: int, count: int) -> list[int]:
        kind = "3:hex" if table == "input" else "4:hex"
        p = self.run("-t", kind, "-r", str(address + 1), "-c", str(count))
        assert p.returncode == 0, f"mbpoll failed: {p.stderr.strip()}"
        got = self.results(p)
        assert sorted(got) == list(range(address + 1, address + count + 1)), p.stdout
        return [int(got[address + 1 + i], 16) for i in range(count)]

    def float(self, table: str, address: int) -> float:
        kind = "3:float" if table == "input" else "4:float"
        p = self.run("-t", kind, "-B", "-r", str(address + 1))
        assert p.returncode == 0, f"mbpoll failed: {p.stderr.strip()}"
        return float(self.results(p)[address + 1])

    def u32(self, address: int) -> int:
        hi, lo = self.words("input", address, 2)
        return hi << 16 | lo

    # writes -----------------------------------------------------------------------------------
    def write_float(self, address: int, value) -> subprocess.CompletedProcess:
        return self.run("-t", "4:float", "-B", "-r", str(address + 1), values=(value,))


def _refused(p: subprocess.CompletedProcess, message: str) -> bool:
    return p.returncode != 0 and message in (p.stdout + p.stderr)


def _decode_model(words: list[int]) -> str:
    return b"".join(struct.pack(">H", w) for w in words).rstrip(b"\0").decode("ascii")


def _serve(request, tmp_path_factory, rig: str):
    transport = request.param
    if transport == "rtu" and SOCAT is None:
        pytest.skip("socat is not installed (apt-get install socat; .ci/run does)")
    cable = PtyPair(tmp_path_factory.mktemp(f"{rig}-pty"), socat=SOCAT) if transport == "rtu" else None
    try:
        if transport == "tcp":
            proc = RigProcess("--rig", rig, "--port", "0", cwd=REPO)
        else:
            proc = RigProcess("--rig", rig, "--no-tcp", "--serial", cable.b, cwd=REPO)
    except BaseException:
        if cable:
            cable.close()
        raise
    yield Mbpoll(transport, proc, cable.a if cable else None)
    alive = proc.alive()
    proc.close()
    if cable:
        cable.close()
    assert alive, "the rig process died during the tests"


@pytest.fixture(scope="module", params=["tcp", "rtu"])
def flutter(request, tmp_path_factory):
    """A real-time flutter rig, served over the parametrised transport only."""
    yield from _serve(request, tmp_path_factory, "flutter")


@pytest.fixture(scope="module", params=["tcp", "rtu"])
def oscillator(request, tmp_path_factory):
    yield from _serve(request, tmp_path_factory, "oscillator")


AIRSPEED = M.BY_NAME["airspeed"].address            # 12 -> mbpoll -r 13
FORCING = M.BY_NAME["forcing_amplitude"].address    # 14 -> mbpoll -r 15


# ---- flutter -----------------------------------------------------------------------------
def test_identification(flutter):
    w = flutter.words("input", 0, 16)
    assert _decode_model(w[0:8]) == "VCL-FLUTTER-2DOF"
    assert w[8] == M.FIRMWARE_VERSION == 100
    assert w[9] == M.MAP_VERSION == 1
    assert w[10] == 0                                   # rig_kind: flutter aerofoil
    assert w[11:13] == f32_words(5000.0)                # sample_rate, the aerofoil board's loop rate
    assert w[13:16] == [M.RING_CAPACITY, M.RING_RECORD, M.RING_BASE]
    assert flutter.float("input", 11) == 5000.0         # mbpoll's own float decoding agrees


def test_measurements_move_in_real_time(flutter):
    rate = 5000.0
    t0 = time.monotonic()
    s1 = flutter.u32(102)                               # sample_seq
    t1 = time.monotonic()
    time.sleep(0.5)
    t2 = time.monotonic()
    s2 = flutter.u32(102)
    t3 = time.monotonic()
    # the counter advances with the wall clock: between the two reads it must have
    # moved at least (most of) the inner interval and at most the outer one
    assert s2 > s1
    assert s2 - s1 <= rate * (t3 - t0) + 0.05 * rate
    assert s2 - s1 >= 0.5 * rate * (t2 - t1)

    status = flutter.words("input", 100, 1)[0]
    assert status >> M.STATUS_BITS["running"] & 1
    assert not status >> M.STATUS_BITS["lockstep"] & 1

    # at rest (no noise, no forcing, not armed) x is sensor noise: sd 5e-5 m, 16-bit ADC
    xs = [flutter.float("input", 200) for _ in range(5)]
    assert all(math.isfinite(x) and abs(x) < 1e-3 for x in xs), xs
    assert len(set(xs)) > 1, f"x does not move: {xs}"


def test_airspeed_write_reads_back_exactly(flutter):
    for value in (17.3, 3.0625):
        p = flutter.write_float(AIRSPEED, value)
        assert p.returncode == 0 and "Written 1 references" in p.stdout, p.stderr
        assert flutter.words("holding", AIRSPEED, 2) == f32_words(value)
        assert flutter.float("holding", AIRSPEED) == pytest.approx(value, rel=1e-6)


@pytest.mark.parametrize("bad", ["99", "40.5", "nan"])
def test_out_of_range_airspeed_is_refused_and_changes_nothing(flutter, bad):
    p = flutter.write_float(AIRSPEED, 21.5)
    assert p.returncode == 0, p.stderr
    before = flutter.words("holding", AIRSPEED, 2)
    assert before == f32_words(21.5)

    p = flutter.write_float(AIRSPEED, bad)
    assert _refused(p, "Illegal data value"), (p.returncode, p.stdout, p.stderr)
    assert flutter.words("holding", AIRSPEED, 2) == before


def test_unmapped_addresses_are_refused(flutter):
    # holding 26..29 are a gap in the map; input 50 likewise
    p = flutter.run("-t", "4", "-r", "27")
    assert _refused(p, "Illegal data address"), p.stderr
    p = flutter.run("-t", "3", "-r", "51", "-c", "2")
    assert _refused(p, "Illegal data address"), p.stderr
    # forcing_amplitude exists on the oscillator only
    p = flutter.run("-t", "4:float", "-B", "-r", str(FORCING + 1))
    assert _refused(p, "Illegal data address"), p.stderr
    # writes: to the gap, and half of a float (FC6 to the airspeed's first word)
    before = flutter.words("holding", AIRSPEED, 2)
    p = flutter.run("-t", "4", "-r", "27", values=(5,))
    assert _refused(p, "Illegal data address"), p.stderr
    p = flutter.run("-t", "4", "-r", str(AIRSPEED + 1), values=(0x4100,))
    assert _refused(p, "Illegal data address"), p.stderr
    assert flutter.words("holding", AIRSPEED, 2) == before


# ---- oscillator ------------------------------------------------------------------------------
def test_oscillator_identification_and_forcing_amplitude(oscillator):
    w = oscillator.words("input", 0, 13)
    assert _decode_model(w[0:8]) == "VCL-EDOSC-1DOF"
    assert w[8:11] == [M.FIRMWARE_VERSION, M.MAP_VERSION, 1]
    assert w[11:13] == f32_words(10000.0)

    for value in (2.75, 61.3):
        p = oscillator.write_float(FORCING, value)
        assert p.returncode == 0 and "Written 1 references" in p.stdout, p.stderr
        assert oscillator.words("holding", FORCING, 2) == f32_words(value)
        assert oscillator.float("holding", FORCING) == pytest.approx(value, rel=1e-6)

    p = oscillator.write_float(FORCING, 150)              # range 0..100 m/s^2
    assert _refused(p, "Illegal data value"), p.stderr
    assert oscillator.words("holding", FORCING, 2) == f32_words(61.3)

    # the airspeed is the aerofoil's
    p = oscillator.run("-t", "4:float", "-B", "-r", str(AIRSPEED + 1))
    assert _refused(p, "Illegal data address"), p.stderr
