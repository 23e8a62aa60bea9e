"""Campaign faults with real processes: SIGKILL and resume, a rig restarted under the
controller, an amplitude trip, and a campaign over Modbus RTU through a pty pair."""

from __future__ import annotations

import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from cbc_controller.log import read_campaign
from rig_sim.physics.truth import flutter_lco_at, flutter_lco_branch

REPO = Path(__file__).resolve().parents[1]

SHORT = """
[campaign]
name = "short"
rig = "flutter"
seed = 3
[rig]
lockstep = true
[loop]
lockstep_slice_s = 0.2
reconnect_s = 20
[parameter]
values = {values}
[cbc]
kp = 200.0
kd = 60.0
navg = 6
{extra}
"""


def campaign(tmp_path, values="[18.5, 20.5, 22.3]", extra="") -> Path:
    p = tmp_path / "short.toml"
    p.write_text(SHORT.format(values=values, extra=extra))
    return p


class Controller:
    """`cbc-campaign run` as a process, with its progress (stderr) collected."""

    def __init__(self, *args):
        self.proc = subprocess.Popen([sys.executable, "-m", "cbc_controller.cli", "run", *args],
                                     stdout=subprocess.PIPE, stderr=subprocess.PIPE, cwd=REPO)
        self.err = b""
        self._t = threading.Thread(target=self._pump, daemon=True)
        self._t.start()

    def _pump(self):
        while True:
            chunk = self.proc.stderr.read1(4096)
            if not chunk:
                return
            self.err += chunk

    def wait_for(self, text: str, timeout: float = 300) -> None:
        t0 = time.time()
        while text.encode() not in self.err:
            if self.proc.poll() is not None:
                raise AssertionError(f"controller ended early: {self.err.decode()[-2000:]}")
            if time.time() - t0 > timeout:
                raise AssertionError(f"no {text!r} within {timeout} s")
            time.sleep(0.05)

    def finish(self, timeout: float = 600) -> int:
        rc = self.proc.wait(timeout=timeout)
        self._t.join(timeout=5)
        return rc


@pytest.fixture(scope="module")
def truth():
    return flutter_lco_branch(V_max=24.5)


def _check_points(path, truth, n_expected=None):
    camp = read_campaign(str(path))
    keys = [p["key"] for p in camp.points]
    assert len(keys) == len(set(keys)), "duplicated points"
    assert [p["index"] for p in camp.points] == list(range(len(keys))), "lost or reordered points"
    if n_expected is not None:
        assert len(keys) == n_expected, keys
    for p in camp.points:
        ref = flutter_lco_at(p["parameter"], truth)["stable" if p["stable"] else "unstable"]
        assert ref is not None and p["amplitude"] == pytest.approx(ref, rel=0.01), p["key"]
    return camp


def test_sigkill_then_resume_loses_and_duplicates_nothing(tmp_path, truth):
    out = tmp_path / "killed.h5"
    c = Controller(str(campaign(tmp_path)), "--out", str(out))
    c.wait_for("[3 points")                       # mid-campaign: the second airspeed is done
    time.sleep(0.7)                                # ... and the third under way
    c.proc.send_signal(signal.SIGKILL)
    c.finish()
    n_before = len(read_campaign(str(out)).points)
    assert 3 <= n_before < 6
    r = subprocess.run([sys.executable, "-m", "cbc_controller.cli", "run", "--resume", str(out),
                        "--quiet"], capture_output=True, text=True, cwd=REPO, timeout=600)
    assert r.returncode == 0, r.stderr
    camp = _check_points(out, truth, n_expected=6)
    assert {p["parameter"] for p in camp.points} == {18.5, 20.5, 22.3}
    assert len(camp.runs) == 2


def test_rig_restart_mid_campaign_reconnects_and_goes_on(tmp_path, truth, rig_process):
    from rig_sim.harness import RigProcess
    rig = rig_process("--rig", "flutter", "--lockstep", "--seed", "3")
    port = rig.port
    out = tmp_path / "restart.h5"
    c = Controller(str(campaign(tmp_path)), "--rig", f"tcp://127.0.0.1:{port}", "--out", str(out))
    c.wait_for("[2 points")
    rig.stop()                                      # the rig goes away mid-campaign ...
    time.sleep(1.0)
    rig2 = RigProcess("--rig", "flutter", "--lockstep", "--seed", "3", "--port", str(port))
    try:                                            # ... and comes back on the same port
        assert c.finish() == 0, c.err.decode()[-2000:]
    finally:
        rig2.stop()
    camp = _check_points(out, truth)
    assert len(camp.points) == 6
    texts = " ".join(str(e) for e in camp.events)
    assert "lost" in texts and "restored" in texts, camp.events
    assert "interrupted" in texts                   # the interrupted airspeed is marked


def test_the_link_follows_the_clock_of_the_rig_that_answers(rig_process):
    """A rig back on the same address may run on the other clock: each take of control sets
    the link for the rig that answered (a lockstep rig's long wait, never retried, must not
    stay on a real-time rig, whose lost link it would hide for the whole reconnect window)."""
    from cbc_controller.client import RigClient
    from cbc_controller.engine import REALTIME_ANSWER_S, REALTIME_RETRIES, Engine, LoopOptions
    from rig_sim.harness import RigProcess
    lockstep = rig_process("--rig", "flutter", "--lockstep")
    port = lockstep.port
    engine = Engine(RigClient(lockstep.url, timeout=1.0, retries=1), LoopOptions(reconnect_s=7.0))
    engine.start()
    assert engine.lockstep and engine.rig.link == (7.0, 0)
    engine.close()
    lockstep.stop()
    realtime = RigProcess("--rig", "flutter", "--port", str(port))
    try:
        engine.start()
        assert not engine.lockstep
        assert engine.rig.link == (REALTIME_ANSWER_S, REALTIME_RETRIES)
        engine.close()
    finally:
        realtime.stop()


def test_a_lockstep_rig_slow_to_answer_is_waited_for_and_the_campaign_repeats(
        tmp_path, rig_process):
    """A lockstep rig stopped (SIGSTOP) mid-campaign for longer than a real-time link's
    timeout and retry: a busy machine, not a lost link. The controller waits, sends
    nothing twice, and logs the points of the same campaign run against an unstopped rig
    with the same seed, bit for bit, with no link event."""
    points = {}
    for paused in (False, True):
        rig = rig_process("--rig", "flutter", "--lockstep", "--seed", "3")
        out = tmp_path / f"paused-{paused}.h5"
        c = Controller(str(campaign(tmp_path, "[20.5]")), "--rig",
                       f"tcp://127.0.0.1:{rig.port}", "--out", str(out))
        if paused:
            c.wait_for("[1 points")
            rig.proc.send_signal(signal.SIGSTOP)
            time.sleep(6.0)                     # > 2 s timeout x (1 + 1 retry)
            rig.proc.send_signal(signal.SIGCONT)
        assert c.finish() == 0, c.err.decode()[-2000:]
        camp = read_campaign(str(out))
        assert not [e for e in camp.events if "link" in str(e)], camp.events
        points[paused] = [(p["key"], p["amplitude"], p["frequency"], p["stable"], p["rig_time"])
                          for p in camp.points]
    assert len(points[False]) == 2 and points[True] == points[False]


def test_a_real_time_rig_stopped_longer_than_its_watchdog_has_the_airspeed_repeated(
        tmp_path, truth, rig_process):
    """In real time a rig stopped for 6 s loses the link, and its watchdog trips (nobody
    could feed the heartbeat). The trip is logged, and the airspeed is measured again as
    after any lost link, not abandoned as for a fault of the rig's own."""
    rig = rig_process("--rig", "flutter", "--time-scale", "20", "--seed", "3")
    path = campaign(tmp_path, "[20.5]")
    path.write_text(path.read_text().replace("lockstep = true", "time_scale = 20.0"))
    out = tmp_path / "stopped.h5"
    c = Controller(str(path), "--rig", f"tcp://127.0.0.1:{rig.port}", "--out", str(out))
    c.wait_for("[1 points")
    rig.proc.send_signal(signal.SIGSTOP)
    time.sleep(6.0)
    rig.proc.send_signal(signal.SIGCONT)
    assert c.finish() == 0, c.err.decode()[-2000:]
    camp = _check_points(out, truth, n_expected=2)
    assert {(p["parameter"], bool(p["stable"])) for p in camp.points} == {(20.5, True),
                                                                          (20.5, False)}
    texts = " ".join(str(e) for e in camp.events)
    assert "lost" in texts and "restored" in texts, camp.events
    assert "abandoned" not in texts, camp.events


def test_amplitude_trip_is_logged_and_the_campaign_goes_on(tmp_path, truth):
    # the trip acts on |x|: the stable cycle at 18.5 m/s peaks near 73 mm (63 mm first
    # harmonic on a 9 mm DC), the one at 20.5 m/s near 86 mm; trip between them
    out = tmp_path / "trip.h5"
    r = subprocess.run([sys.executable, "-m", "cbc_controller.cli", "run",
                        str(campaign(tmp_path, "[18.5, 20.5]", "trip = 0.08")), "--out", str(out),
                        "--quiet"], capture_output=True, text=True, cwd=REPO, timeout=600)
    assert r.returncode == 0, r.stderr
    camp = _check_points(out, truth)
    faults = [e for e in camp.events if "code" in str(e) and "amplitude trip" in str(e)]
    assert faults, camp.events
    at = {(p["parameter"], p["stable"]) for p in camp.points}
    assert (18.5, True) in at and (18.5, False) in at
    assert (20.5, False) in at                      # found before the trip
    assert (20.5, True) not in at                   # beyond the trip level: not collected
    assert all(p["amplitude"] < 0.08 for p in camp.points)


def test_campaign_over_modbus_rtu(tmp_path, truth, pty_pair, rig_process):
    rig_process("--rig", "flutter", "--lockstep", "--seed", "3", "--no-tcp", "--serial", pty_pair.b)
    out = tmp_path / "rtu.h5"
    r = subprocess.run([sys.executable, "-m", "cbc_controller.cli", "run",
                        str(campaign(tmp_path, "[20.5]")), "--rig", f"serial://{pty_pair.a}",
                        "--out", str(out), "--quiet"],
                       capture_output=True, text=True, cwd=REPO, timeout=600)
    assert r.returncode == 0, r.stderr
    camp = _check_points(out, truth, n_expected=2)
    assert camp.metadata["rig_url"].startswith("serial://")
