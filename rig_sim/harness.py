"""Run the rig service as a separate process, and make a null-modem cable for it.

Used by the tests and the benchmarks (real subprocesses, real sockets and ptys);
also handy in a notebook. `RigProcess` starts `rig-sim serve ...` and returns once
the service has announced its endpoints; `PtyPair` links two pseudo-terminals with
socat, one end for the rig's `--serial`, the other for a Modbus RTU client.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path


class RigProcess:
    """`rig-sim serve ARGS...` as a subprocess; ready (endpoints known) on return."""

    def __init__(self, *args: str, cwd: str | Path | None = None, stderr_file: str | Path | None = None):
        """`stderr_file`: where the service's log goes (a pipe nobody reads would fill
        up and stall a `--verbose` service); by default a pipe, read on failure."""
        self.args = [sys.executable, "-m", "rig_sim.cli", "serve", *args]
        self.stderr_file = Path(stderr_file) if stderr_file is not None else None
        with (open(self.stderr_file, "w") if self.stderr_file else contextlib.nullcontext(subprocess.PIPE)) as err:
            self.proc = subprocess.Popen(self.args, stdout=subprocess.PIPE, stderr=err, text=True, cwd=cwd)
        line = self.proc.stdout.readline()
        if not line:
            self.proc.wait()
            raise RuntimeError(f"rig-sim did not start: {self.stderr().strip()}")
        self.info = json.loads(line)
        self.endpoints = self.info["endpoints"]
        self.url = self.endpoints[0]

    @property
    def port(self) -> int:
        return int(self.url.rsplit(":", 1)[1])

    def stderr(self) -> str:
        """The service's log so far (all of it once it has stopped)."""
        if self.stderr_file is not None:
            return self.stderr_file.read_text()
        return self.proc.stderr.read() if self.proc.poll() is not None else ""

    def alive(self) -> bool:
        return self.proc.poll() is None

    def stop(self) -> int:
        """SIGTERM (a clean shutdown), SIGKILL if that takes over 10 s; the exit status."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        return self.proc.returncode

    close = stop


class PtyPair:
    """Two linked pseudo-terminals (`a`, `b`) from socat: a null-modem cable."""

    def __init__(self, folder: str | Path, socat: str = "socat", timeout: float = 20.0):
        self.a = str(Path(folder) / "ttyA")
        self.b = str(Path(folder) / "ttyB")
        for p in (self.a, self.b):
            if os.path.lexists(p):
                os.unlink(p)
        self.proc = subprocess.Popen(
            [socat, f"pty,raw,echo=0,link={self.a}", f"pty,raw,echo=0,link={self.b}"],
            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        deadline = time.monotonic() + timeout          # generous: a loaded machine is slow
        while not (os.path.exists(self.a) and os.path.exists(self.b)):
            if self.proc.poll() is not None:
                raise RuntimeError(f"socat did not create the pty pair: {self.proc.stderr.read()!r}")
            if time.monotonic() > deadline:
                self.close()
                raise RuntimeError(f"socat did not create the pty pair within {timeout:g} s")
            time.sleep(0.02)

    def close(self) -> None:
        self.proc.terminate()
        self.proc.wait(timeout=5)
