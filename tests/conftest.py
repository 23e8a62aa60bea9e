"""Shared fixtures: real rig-sim service processes, socat pty pairs."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


class RigProcess:
    """A `rig-sim serve` subprocess; `url` once it has announced readiness."""

    def __init__(self, *args: str, timeout: float = 90.0):
        self.args = [sys.executable, "-m", "rig_sim.cli", "serve", *args]
        self.proc = subprocess.Popen(self.args, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                     text=True, cwd=REPO)
        line = self.proc.stdout.readline()
        if not line:
            err = self.proc.stderr.read()
            raise RuntimeError(f"rig-sim did not start: {err.strip()}")
        self.info = json.loads(line)
        self.endpoints = self.info["endpoints"]
        self.url = self.endpoints[0]

    @property
    def port(self) -> int:
        return int(self.url.rsplit(":", 1)[1])

    def stop(self) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        return self.proc.returncode


@pytest.fixture
def rig_process():
    """Factory: start rig-sim with the given CLI args (always --port 0 unless given)."""
    started: list[RigProcess] = []

    def start(*args: str) -> RigProcess:
        if "--port" not in args and "--no-tcp" not in args:
            args = (*args, "--port", "0")
        p = RigProcess(*args)
        started.append(p)
        return p

    yield start
    for p in started:
        p.stop()


class PtyPair:
    """Two linked pseudo-terminals from socat (a null-modem cable)."""

    def __init__(self, tmp: Path):
        if shutil.which("socat") is None:
            pytest.skip("socat is not installed (.ci/run installs it)")
        self.a = str(tmp / "ttyA")
        self.b = str(tmp / "ttyB")
        self.proc = subprocess.Popen(
            ["socat", f"pty,raw,echo=0,link={self.a}", f"pty,raw,echo=0,link={self.b}"])
        for _ in range(400):                 # up to 20 s on a loaded machine
            if os.path.exists(self.a) and os.path.exists(self.b):
                break
            time.sleep(0.05)
        else:
            raise RuntimeError("socat did not create the pty pair")

    def close(self):
        self.proc.terminate()
        self.proc.wait(timeout=5)


@pytest.fixture
def pty_pair(tmp_path):
    pair = PtyPair(tmp_path)
    yield pair
    pair.close()
