"""Shared fixtures: real rig-sim service processes, socat pty pairs."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from rig_sim.harness import PtyPair, RigProcess

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture
def rig_process():
    """Factory: start rig-sim with the given CLI args (always --port 0 unless given)."""
    started: list[RigProcess] = []

    def start(*args: str) -> RigProcess:
        if "--port" not in args and "--no-tcp" not in args:
            args = (*args, "--port", "0")
        p = RigProcess(*args, cwd=REPO)
        started.append(p)
        return p

    yield start
    for p in started:
        p.stop()


@pytest.fixture
def pty_pair(tmp_path):
    if shutil.which("socat") is None:
        pytest.skip("socat is not installed (.ci/run installs it)")
    pair = PtyPair(tmp_path)
    yield pair
    pair.close()
