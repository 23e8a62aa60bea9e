"""The rig service over Modbus TCP with a real client: safety, control ownership,
lockstep determinism, and the CLI's handling of bad input."""

from __future__ import annotations

import signal
import socket
import subprocess
import sys
import time

import numpy as np
import pytest

from cbc_controller.client import RigClient, RigError
from rig_sim.device import register_map as M

BUSY, ILLEGAL_FUNCTION, ILLEGAL_ADDRESS, ILLEGAL_VALUE, DEVICE_FAILURE = 6, 1, 2, 3, 4


def status_bits(word: int) -> set[str]:
    return {name for name, bit in M.STATUS_BITS.items() if word >> bit & 1}


def connect(url: str) -> RigClient:
    c = RigClient(url, timeout=2.0)
    c.connect()
    return c


# ---------------------------------------------------------------- watchdog ----------
def test_watchdog_zeroes_output_and_latches_fault(rig_process):
    rig = rig_process("--rig", "flutter", "--time-scale", "2")
    c = connect(rig.url)
    c.write(watchdog_timeout=0.3, kp=1000.0, kd=20.0, airspeed=15.0, target_a1=0.02)
    c.write(command=1)                           # arm
    for i in range(10):                          # a live host: heartbeat every 0.1 s
        c.write(heartbeat=i + 1)
        time.sleep(0.1)
    r = c.read("status", "fault_code", "control_now")
    assert "armed" in status_bits(r["status"]) and r["fault_code"] == 0
    assert abs(r["control_now"]) > 0.0          # it is actually driving
    time.sleep(1.0)                              # the host goes silent
    r = c.read("status", "fault_code", "control_now", "watchdog_trips", "x")
    assert r["fault_code"] == 2, r                # watchdog fault latched
    assert "armed" not in status_bits(r["status"])
    assert r["control_now"] == 0.0               # output zeroed
    assert r["watchdog_trips"] == 1
    # the latch holds: arming is refused until the fault is reset
    with pytest.raises(RigError) as e:
        c.write(command=1)
    assert e.value.code == DEVICE_FAILURE
    c.write(command=3)                           # reset fault
    c.write(command=1)
    assert "armed" in status_bits(c.get("status"))
    c.write(command=2)
    c.close()


def test_watchdog_frees_control_of_a_silent_client(rig_process):
    rig = rig_process("--rig", "flutter", "--time-scale", "1")
    a, b = connect(rig.url), connect(rig.url)
    a.write(watchdog_timeout=0.2)
    a.write(control=1)
    assert a.get("control") == 1 and b.get("control") == 2
    with pytest.raises(RigError) as e:
        b.write(airspeed=10.0)
    assert e.value.code == BUSY
    time.sleep(0.6)                              # a stops heart-beating
    assert b.get("control") == 0
    b.write(airspeed=10.0)                       # now b may take over
    assert b.get("airspeed") == 10.0 and a.get("control") == 2
    a.close()
    b.close()


# ---------------------------------------------------------------- amplitude trip ----
def test_amplitude_trip_latches_and_disarms(rig_process):
    rig = rig_process("--rig", "flutter", "--lockstep")
    c = connect(rig.url)
    c.write(watchdog_timeout=60.0, airspeed=10.0, trip=0.02, kp=2000.0, kd=30.0,
            phase_mode=0, frequency=2.4)
    c.write(target_a1=0.05)                      # drive the heave well past the trip level
    c.write(command=1)
    c.write(advance=5000)                        # 1 s of rig time
    r = c.read("status", "fault_code", "trips", "control_now")
    assert r["fault_code"] == 1 and r["trips"] == 1
    assert "armed" not in status_bits(r["status"]) and "fault" in status_bits(r["status"])
    assert r["control_now"] == 0.0
    # with the output off the heave decays below the trip level, but the fault stays latched
    c.write(advance=100000)
    r = c.read("fault_code", "x")
    assert r["fault_code"] == 1 and abs(r["x"]) < 0.02
    c.write(command=3)
    assert c.get("fault_code") == 0
    c.close()


# ---------------------------------------------------------------- one controller ----
def test_only_one_client_holds_control(rig_process):
    rig = rig_process("--rig", "oscillator", "--lockstep")
    a, b = connect(rig.url), connect(rig.url)
    a.write(control=1)
    before = b.read("forcing_amplitude", "kp", "target_a1")
    for kw in ({"forcing_amplitude": 5.0}, {"kp": 100.0}, {"target_a1": 0.001}, {"command": 1},
               {"advance": 10}, {"heartbeat": 7}):
        with pytest.raises(RigError) as e:
            b.write(**kw)
        assert e.value.code == BUSY, kw
    assert b.read("forcing_amplitude", "kp", "target_a1") == before   # nothing changed
    with pytest.raises(RigError):
        b.write(control=0)                      # b cannot release a's control
    # reads stay open to everyone
    assert b.get("model") == "VCL-EDOSC-1DOF"
    a.write(forcing_amplitude=5.0)
    assert b.get("forcing_amplitude") == 5.0
    a.write(control=0)                          # release
    b.write(kp=100.0)                           # b takes control implicitly
    assert b.get("control") == 1 and a.get("control") == 2
    b.close()                                    # disconnecting gives control back
    time.sleep(0.3)
    assert a.get("control") == 0
    a.close()


def test_requests_a_client_sent_before_it_went_do_not_keep_control(rig_process):
    """A controller that gives up on a write the rig has not read yet (here the rig is
    stopped, as a busy machine may stop it) and leaves: the write is served after the
    disconnect, and control still goes back. In lockstep nothing else would free it (the
    watchdog counts simulated time, which only a controller advances)."""
    rig = rig_process("--rig", "flutter", "--lockstep")
    a = RigClient(rig.url, timeout=0.5, retries=0)
    a.connect()
    a.write(control=1)
    rig.proc.send_signal(signal.SIGSTOP)
    try:
        with pytest.raises(RigError):
            a.write(heartbeat=5)                # unanswered: the rig is stopped
        a.close()
    finally:
        rig.proc.send_signal(signal.SIGCONT)
    time.sleep(0.3)
    b = connect(rig.url)
    b.write(control=1)
    assert b.get("control") == 1
    assert b.get("heartbeat") == 5              # the write was served all the same
    b.close()


# ---------------------------------------------------------------- protocol errors ---
def test_bad_writes_answer_exceptions_and_change_nothing(rig_process):
    rig = rig_process("--rig", "flutter", "--lockstep")
    c = connect(rig.url)
    settings = [r.name for r in M.REGISTERS if r.table == "holding" and r.applies_to("flutter")]
    before = c.read(*settings)
    cases = [
        (M.BY_NAME["airspeed"].address, M.f32_words(41.0), ILLEGAL_VALUE),
        (M.BY_NAME["airspeed"].address, M.f32_words(float("nan")), ILLEGAL_VALUE),
        (M.BY_NAME["kp"].address, M.f32_words(float("inf")), ILLEGAL_VALUE),
        (M.BY_NAME["navg"].address, [0], ILLEGAL_VALUE),
        (M.BY_NAME["command"].address, [9], ILLEGAL_VALUE),
        (M.BY_NAME["forcing_amplitude"].address, M.f32_words(1.0), ILLEGAL_ADDRESS),  # not this rig
        (M.BY_NAME["kp"].address + 1, [0], ILLEGAL_ADDRESS),      # half a float
        (26, [1, 2], ILLEGAL_ADDRESS),                           # unmapped
        (900, [1], ILLEGAL_ADDRESS),
    ]
    for address, words, code in cases:
        with pytest.raises(RigError) as e:
            c.write_words(address, words)
        assert e.value.code == code, (address, words)
    # a multi-register write with one bad value changes none of the others
    kp = M.BY_NAME["kp"]
    words = M.f32_words(500.0) + M.f32_words(3.0) + M.f32_words(2.0) + M.f32_words(99.0)
    with pytest.raises(RigError) as e:
        c.write_words(kp.address, words)         # kp, kd, frequency, airspeed(bad)
    assert e.value.code == ILLEGAL_VALUE
    assert c.read(*settings) == before
    with pytest.raises(RigError) as e:
        c.read_words("input", 30, 4)             # unmapped input registers
    assert e.value.code == ILLEGAL_ADDRESS
    with pytest.raises(RigError) as e:
        c.write_words(M.BY_NAME["advance"].address, [0, 0])
    assert e.value.code == ILLEGAL_VALUE         # advance 0 is out of range
    assert c.read(*settings) == before
    c.close()


def test_advance_is_refused_outside_lockstep(rig_process):
    rig = rig_process("--rig", "flutter", "--time-scale", "1")
    c = connect(rig.url)
    with pytest.raises(RigError) as e:
        c.write(advance=100)
    assert e.value.code == ILLEGAL_FUNCTION
    assert "running" in status_bits(c.get("status"))
    c.close()


# ---------------------------------------------------------------- lockstep ----------
def _lockstep_session(rig_process, seed: int) -> tuple[np.ndarray, list[int]]:
    rig = rig_process("--rig", "flutter", "--lockstep", "--noise", "0.02", "--seed", str(seed))
    c = connect(rig.url)
    c.write(watchdog_timeout=60.0, airspeed=23.0, kp=2000.0, kd=40.0, frequency=2.4)
    c.write(target_a1=0.06)
    c.write(command=1)
    c.pull_ring()                                # start pulling at the current head
    samples = []
    for i in range(8):
        c.write(heartbeat=i + 1)
        c.write(advance=2000)
        block = c.pull_ring()
        assert block.gap == 0
        assert np.all(np.diff(block.sample) == 1)
        samples.append(np.column_stack([block.data[f] for f in ("x", "x_dot", "q2", "target", "control")]))
    fourier = c.read_words("input", M.CHANNEL_BASE["response"], 62)
    c.close()
    rig.stop()
    return np.concatenate(samples), fourier


class _RigRunsOnDuringTheRead(RigClient):
    """A client whose first ring read is slow: the lockstep rig runs `samples` on before the
    next chunk comes back, as a free-running rig does while a busy host reads."""

    def __init__(self, url: str, samples: int):
        super().__init__(url, timeout=2.0)
        self.samples_during_read = samples

    def read_words(self, table, address, count):
        words = super().read_words(table, address, count)
        if table == "input" and address >= M.RING_BASE and self.samples_during_read:
            n, self.samples_during_read = self.samples_during_read, 0
            self.write(advance=n)
        return words


def test_ring_records_overwritten_during_a_slow_read_are_dropped_and_counted(rig_process):
    # The first pull's records reach back cap - 64 behind the head; 300 samples written while
    # the first chunk is read overwrite the oldest ~236 of them, chunks not yet read included.
    # Kept, they carried the sample numbers of a lap later (a jump of 4096 records forward,
    # then back), which dated a raw record wrongly in a resumed campaign.
    rig = rig_process("--rig", "flutter", "--lockstep", "--seed", "3")
    c = _RigRunsOnDuringTheRead(rig.url, samples=0)
    c.connect()
    c.write(watchdog_timeout=60.0, airspeed=23.0, ring_decimation=1)
    c.pull_ring()                                # start at the current head
    c.write(advance=M.RING_CAPACITY)             # more than the clearance: 64 lost already
    head = c.get("ring_head")
    c.samples_during_read = 300
    block = c.pull_ring()
    assert c.get("ring_head") == head + 300
    assert np.all(np.diff(block.sample) == 1)    # one contiguous, correctly dated stretch
    assert block.sample[-1] == c.get("sample_seq") - 300 - 1
    # every record is either kept or counted as lost, and nothing that survived is dropped
    assert block.first_record + len(block.sample) == head
    assert block.gap + len(block.sample) == M.RING_CAPACITY
    assert block.first_record == head + 300 - M.RING_CAPACITY + 1
    # what was kept is what the rig still holds for those records
    again = c.read_words("input", M.ring_address(block.first_record), M.RING_RECORD)
    assert again[0] == block.sample[0] % 65536
    c.close()
    rig.stop()


def test_lockstep_same_seed_is_bit_for_bit_reproducible(rig_process):
    a, fa = _lockstep_session(rig_process, seed=7)
    b, fb = _lockstep_session(rig_process, seed=7)
    c, fc = _lockstep_session(rig_process, seed=8)
    assert a.shape == (16000, 5)
    assert np.array_equal(a, b) and fa == fb     # bit for bit
    assert not np.array_equal(a, c)               # and the seed matters
    assert np.std(a[:, 0]) > 0.01                 # it really oscillated


# ---------------------------------------------------------------- CLI -----------------
def _run_cli(*args, timeout=60):
    return subprocess.run([sys.executable, "-m", "rig_sim.cli", *args], capture_output=True,
                          text=True, timeout=timeout)


@pytest.mark.parametrize("args, needle", [
    (("serve", "--rig", "glider"), "invalid choice"),
    (("serve", "--rig", "flutter", "--time-scale", "-3"), "positive"),
    (("serve", "--rig", "flutter", "--noise", "abc"), "not a number"),
    (("serve", "--rig", "flutter", "--port", "70000"), "0..65535"),
    (("serve", "--rig", "flutter", "--lockstep", "--time-scale", "5"), "not allowed"),
    (("serve", "--rig", "flutter", "--effect", "turbulence=1"), "unknown effect"),
    (("serve", "--rig", "flutter", "--effect", "freeplay"), "NAME=VALUE"),
    (("serve", "--rig", "flutter", "--effect", "freeplay=-1"), ">= 0"),
    (("serve", "--rig", "flutter", "--physics", "lift=1"), "not a parameter of the flutter"),
    (("serve", "--rig", "flutter", "--physics", "c1"), "NAME=VALUE"),
    (("serve", "--rig", "flutter", "--physics", "c1=nan"), "finite"),
    (("serve", "--rig", "oscillator", "--physics", "zeta=x"), "not a number"),
    (("serve", "--rig", "flutter", "--physics", "c1=0", "c1=0.1"), "given twice"),
    (("serve", "--rig", "flutter", "--effect-plugin", "/nonexistent/plug.py:force"), "file not found"),
    (("serve", "--rig", "flutter", "--serial", "/nonexistent/tty"), "does not exist"),
    (("serve", "--rig", "flutter", "--unit", "0"), "1..247"),
    (("serve", "--rig", "flutter", "--unit", "248"), "1..247"),
    (("serve", "--rig", "flutter", "--unit", "one"), "1..247"),
    (("frobnicate",), "invalid choice"),
])
def test_cli_bad_input_is_one_line_and_exit_2(args, needle):
    r = _run_cli(*args)
    assert r.returncode == 2, r
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1, r.stderr
    assert needle in lines[0], lines[0]
    assert "Traceback" not in r.stderr


def test_cli_port_in_use(tmp_path):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        r = _run_cli("serve", "--rig", "flutter", "--port", str(port))
    assert r.returncode == 2
    assert r.stderr.strip() == f"rig-sim: error: port {port} on 127.0.0.1 is already in use"


def test_cli_plugin_with_wrong_arity_output(tmp_path):
    plug = tmp_path / "plug.py"
    plug.write_text("def force(t, q, qd, params):\n    return [1.0, 2.0, 3.0]\n")
    r = _run_cli("serve", "--rig", "flutter", "--effect-plugin", f"{plug}:force")
    assert r.returncode == 2 and "must return 2 force(s)" in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1


def test_registers_command_matches_the_map():
    r = _run_cli("registers", "--format", "json")
    assert r.returncode == 0
    import json
    doc = json.loads(r.stdout)
    assert [x["name"] for x in doc["registers"]] == [x.name for x in M.REGISTERS]
    md = _run_cli("registers").stdout
    assert "| holding | 12 | `airspeed` | f32 | m/s | rw | 0..40 | flutter |" in md
