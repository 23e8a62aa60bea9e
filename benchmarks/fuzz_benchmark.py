#!/usr/bin/env python
"""The rig under a storm of mutated Modbus frames; prints one JSON object on stdout.

100,000 frames over Modbus TCP (flutter rig) and 10,000 over Modbus RTU through a
socat pty pair (oscillator rig), both in --lockstep and --verbose, from the seeded
generator and datasheet model of tests/fuzz_frames.py, run by tests/rig_fuzzing.py
(which checks every answer as it goes; tests/test_rig_fuzz.py runs a smaller
storm). Reported per
transport:
- settings_unchanged: every holding register read back (a real client, every 200
  frames and at the end) equals its value before the storm;
- answers_after: the rig still serves that client correctly (a write read back);
- rss_kib before/after: resident memory of the rig process;
- exception_codes: the codes seen in the answers, with counts;
- latency: TCP, FC4 reads of the status word by a second master on its own
  connection during the storm and after it; RTU (one line, no second master), the
  answered fuzz frames during the storm and FC4 status reads after it;
- tracebacks: in the rig's --verbose log (a request raising inside the server).

Usage: python benchmarks/fuzz_benchmark.py [--tcp-frames N] [--rtu-frames N] [--seed S]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import rig_sim  # noqa: E402
from rig_sim.harness import PtyPair, RigProcess  # noqa: E402
from tests.rig_fuzzing import SEED, run_rtu, run_tcp  # noqa: E402


def log(*args):
    print(*args, file=sys.stderr, flush=True)


def _with_log(rig: RigProcess, out: dict) -> dict:
    rig.stop()
    out["tracebacks_in_rig_log"] = rig.stderr().count("Traceback")
    out["rig_exit_status"] = rig.proc.returncode
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tcp-frames", type=int, default=100_000)
    ap.add_argument("--rtu-frames", type=int, default=10_000)
    ap.add_argument("--seed", type=int, default=SEED)
    args = ap.parse_args()
    if shutil.which("socat") is None:
        log("socat is needed for the RTU storm (apt-get install socat)")
        return 2
    import pymodbus

    t0 = time.perf_counter()
    result = {"benchmark": "fuzz_benchmark", "version": rig_sim.__version__, "seed": args.seed,
              "machine": {"nproc": os.cpu_count(), "platform": platform.platform(),
                          "python": platform.python_version(), "pymodbus": pymodbus.__version__}}
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        log(f"TCP: {args.tcp_frames} frames")
        rig = RigProcess("--rig", "flutter", "--lockstep", "--verbose", "--port", "0", cwd=REPO,
                         stderr_file=tmp / "tcp.log")
        try:
            result["tcp"] = _with_log(rig, run_tcp(rig, args.tcp_frames, args.seed))
        finally:
            rig.stop()
        log(f"RTU: {args.rtu_frames} frames")
        cable = PtyPair(tmp)
        rig = RigProcess("--rig", "oscillator", "--lockstep", "--verbose", "--no-tcp", "--serial", cable.b,
                         cwd=REPO, stderr_file=tmp / "rtu.log")
        try:
            result["rtu"] = _with_log(rig, run_rtu(rig, cable, args.rtu_frames, args.seed + 1))
        finally:
            rig.stop()
            cable.close()
    result["runtime_s"] = round(time.perf_counter() - t0, 1)
    print(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
