"""Reproducible resume (issue 20, item 9): a lockstep campaign killed and resumed logs the same
points, bit for bit, as the campaign never interrupted.

The plans measure in segments (an airspeed, a frequency's sweep) that each start with the rig
restarted from rest and its noise streams seeded from the campaign's seed and the segment
(the rig's `noise_seed`). Only the rig's clock differs in a resumed file: a fresh rig counts
its samples from 0, so `rig_time` and the ring's sample numbers are left out of the
comparison; everything measured is compared exactly."""

from __future__ import annotations

import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from cbc_controller.log import read_campaign
from rig_sim.firmware.board import Board, RigOptions

REPO = Path(__file__).resolve().parents[1]
RIG_CLOCK = {"rig_time", "sample"}                 # a fresh rig's clock starts at 0
WALL_CLOCK = {"wall_time", "wall_seconds", "run", "seq", "loop"}

FLUTTER = """
[campaign]
name = "resume"
rig = "flutter"
seed = 7
[rig]
lockstep = true
[loop]
lockstep_slice_s = 0.2
[parameter]
values = [18.5, 20.5, 22.3]
[cbc]
navg = 6
"""

OSCILLATOR = """
[campaign]
name = "resume"
rig = "oscillator"
seed = 7
[rig]
lockstep = true
[frequencies]
values = [21.0, 23.0]
[cbc]
amplitude_stop = 0.004
"""


def differences(a, b, path="") -> list[str]:
    """Where two point documents (as read back) differ, clocks aside."""
    if isinstance(a, dict) and isinstance(b, dict):
        if set(a) != set(b):
            return [f"{path}: fields {sorted(set(a) ^ set(b))}"]
        return [d for k in a if k not in RIG_CLOCK | WALL_CLOCK
                for d in differences(a[k], b[k], f"{path}.{k}")]
    if isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            return [f"{path}: {len(a)} != {len(b)} items"]
        return [d for i, (x, y) in enumerate(zip(a, b)) for d in differences(x, y, f"{path}[{i}]")]
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        same = np.shape(a) == np.shape(b) and np.array_equal(a, b, equal_nan=True)
        return [] if same else [f"{path}: arrays differ"]
    return [] if a == b or (a != a and b != b) else [f"{path}: {a!r} != {b!r}"]


def run(*args, timeout=600):
    r = subprocess.run([sys.executable, "-m", "cbc_controller.cli", "run", *args, "--quiet"],
                       capture_output=True, text=True, cwd=REPO, timeout=timeout)
    assert r.returncode == 0, r.stderr
    return r


def killed_after(toml: Path, out: Path, points: int) -> None:
    """Start the campaign and SIGKILL it once `points` points are logged (mid-segment)."""
    proc = subprocess.Popen([sys.executable, "-m", "cbc_controller.cli", "run", str(toml),
                             "--out", str(out)], stderr=subprocess.PIPE, cwd=REPO)
    seen = b""
    try:
        while f"[{points} points".encode() not in seen:
            chunk = proc.stderr.read1(4096)
            assert chunk, f"the campaign ended before {points} points: {seen.decode()[-500:]}"
            seen += chunk
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()


@pytest.mark.parametrize("text, cut", [(FLUTTER, 3), (OSCILLATOR, 12)], ids=["flutter", "oscillator"])
def test_killed_and_resumed_equals_uninterrupted(tmp_path, text, cut):
    toml = tmp_path / "c.toml"
    toml.write_text(text)
    whole, resumed = tmp_path / "whole.h5", tmp_path / "resumed.h5"
    run(str(toml), "--out", str(whole))
    killed_after(toml, resumed, cut)
    logged = len(read_campaign(str(resumed)).points)
    assert cut <= logged
    run("--resume", str(resumed))
    a, b = read_campaign(str(whole), timeseries=True), read_campaign(str(resumed), timeseries=True)
    assert len(b.runs) == 2 and logged < len(b.points)
    assert [p["key"] for p in a.points] == [p["key"] for p in b.points]
    runs_of = {}                                       # segment -> the runs that logged it
    for p in b.points:
        runs_of.setdefault(p["key"].split("/")[0], set()).add(p["run"])
    assert {0, 1} in runs_of.values(), runs_of         # killed inside a segment
    for p, q in zip(a.points, b.points):
        assert not differences(p, q), (p["key"], differences(p, q)[:5])


def test_noise_seed_restarts_the_board_whatever_came_before():
    """Two boards with different seeds and histories, given the same noise_seed and the same
    settings, run identically from there; the counters go on."""
    boards = [Board(RigOptions(kind="flutter", sigma=0.02, seed=s)) for s in (1, 2)]
    boards[0].set("parameter", 22.0)
    boards[0].arm()
    boards[0].advance(7000)                            # somewhere on an orbit
    boards[1].advance(3000)
    seq = [b.seq for b in boards]
    for b in boards:
        b.set("noise_seed", 12345)
        assert not b.armed and b.get("noise_seed") == 12345
        b.set("parameter", 23.0)
        b.set("kp", 200.0)
        b.arm()
        b.advance(5000)
    assert [b.seq for b in boards] == [s + 5000 for s in seq]
    assert np.array_equal(boards[0].y, boards[1].y) and np.any(boards[0].y != 0)
    assert np.array_equal(boards[0].cmean, boards[1].cmean)
