#!/usr/bin/env python
"""Benchmarks of the virtual rigs; prints one JSON object on stdout (progress on stderr).

(a) realtime_factor: simulated seconds per wall second of `Board.advance` for each
    rig at its default loop rate with process noise (sigma 0.02) and sensor noise
    on; median over repeats. Two chunkings: 0.1 s of simulation per call (the
    kernel's throughput) and 2 ms per call (how the service's pacer feeds it at
    time-scale 1). Also with a catalogue effect (compiled) and with a Python
    plugin force (called once per sample: the slow path).
(b) round_trip_ms: request round trips of a pymodbus client against a real
    `rig-sim serve` (real time, noise on) over Modbus TCP and over Modbus RTU
    through a socat pty pair: one-register read (FC4), the 62-register Fourier
    block (FC4), and FC23 (write heartbeat, read 14 settings). p50/p99/mean.
    Also a minimal raw RTU master (the device's share of the RTU round trip).
(c) ring_pull: samples per second a client (`RigClient.pull_ring` in a loop) pulls
    from the sample ring buffer of a real-time flutter rig run at --time-scale K
    for increasing K, over TCP and RTU; `max_gapless_sps` is the highest rate the
    rig produced while the client kept up (no record lost or torn, and pulling at
    >= 95 % of the production rate, i.e. sustainable beyond the ring's 4096 records).

Usage: python benchmarks/rig_benchmark.py [--quick]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402

import rig_sim  # noqa: E402
from rig_sim.device import register_map as M  # noqa: E402
from rig_sim.firmware.board import Board, RigOptions  # noqa: E402
from rig_sim.harness import PtyPair, RigProcess  # noqa: E402

PLUGIN_SOURCE = '''
import numpy as np

def flutter_force(t, q, qdot, params):
    """cubic heave stiffness and a little pitch damping"""
    return np.array([-2.0e4 * q[0] ** 3, -0.01 * qdot[1]])

def oscillator_force(t, q, qdot, params):
    """cubic spring"""
    return np.array([-1.0e7 * q[0] ** 3])
'''

CATALOGUE_EFFECT = {"flutter": "freeplay=0.005", "oscillator": "cubic=1e7"}


def log(*args):
    print(*args, file=sys.stderr, flush=True)


def percentile(xs, q):
    return float(np.percentile(np.asarray(xs), q))


# ---- (a) real-time factor --------------------------------------------------------------------
def realtime_factor(kind: str, sim_s: float, repeats: int, chunk_s: float, effects=(), plugin=None) -> dict:
    options = RigOptions(kind=kind, sigma=0.02, seed=7, effects=list(effects), plugin=plugin, sensor_noise=True)
    Board(options).advance(1)                     # compile, or load the cached kernel
    walls = []
    for r in range(repeats):
        board = Board(options)
        n = int(round(sim_s * board.rate))
        chunk = max(1, int(round(chunk_s * board.rate)))
        t0 = time.perf_counter()
        done = 0
        while done < n:
            m = min(chunk, n - done)
            board.advance(m)
            done += m
        walls.append(time.perf_counter() - t0)
        assert np.all(np.isfinite(board.true_state()))
    med = statistics.median(walls)
    return {"rate_hz": board.rate, "sim_s": sim_s, "chunk_samples": chunk, "repeats": repeats,
            "wall_s_median": round(med, 4), "realtime_factor_median": round(sim_s / med, 1),
            "realtime_factor_all": [round(sim_s / w, 1) for w in walls]}


def bench_realtime(quick: bool, tmp: Path) -> dict:
    plugin_file = tmp / "bench_plugin.py"
    plugin_file.write_text(PLUGIN_SOURCE)
    out = {}
    for kind in ("flutter", "oscillator"):
        log(f"(a) real-time factor: {kind}")
        sim = 1.0 if quick else 4.0
        out[kind] = {
            "noise": realtime_factor(kind, sim, 3 if quick else 5, 0.1),
            "noise_pacer_chunks": realtime_factor(kind, sim / 2, 3, 0.002),
            "noise_catalogue_effect": dict(realtime_factor(kind, sim, 3 if quick else 5, 0.1,
                                                           effects=[CATALOGUE_EFFECT[kind]]),
                                           effect=CATALOGUE_EFFECT[kind]),
            "noise_plugin_effect": dict(realtime_factor(kind, 0.2 if quick else 0.5, 3, 0.1,
                                                        plugin=f"{plugin_file}:{kind}_force"),
                                        plugin=f"{kind}_force (Python, one call per sample)"),
        }
    return out


# ---- serving --------------------------------------------------------------------------------------
def _stats(lat_s: list[float]) -> dict:
    ms = [x * 1e3 for x in lat_s]
    return {"n": len(ms), "p50_ms": round(percentile(ms, 50), 3), "p99_ms": round(percentile(ms, 99), 3),
            "mean_ms": round(statistics.fmean(ms), 3)}


def _time_requests(client, n: int) -> dict:
    def fc4_one():
        return client.read_input_registers(100, count=1, device_id=1)

    def fc4_fourier():
        return client.read_input_registers(M.CHANNEL_BASE["response"], count=62, device_id=1)

    beat = [0]

    def fc23():
        beat[0] = (beat[0] + 1) & 0xFFFF
        return client.readwrite_registers(read_address=0, read_count=14, write_address=2,
                                          values=[beat[0]], device_id=1)

    out = {}
    for name, fn in (("read_1_register_fc4", fc4_one), ("read_62_register_fourier_block_fc4", fc4_fourier),
                     ("fc23_write_heartbeat_read_14", fc23)):
        for _ in range(20):                                   # warm up
            assert not fn().isError()
        lat = []
        for _ in range(n):
            t0 = time.perf_counter()
            rr = fn()
            lat.append(time.perf_counter() - t0)
            assert not rr.isError(), rr
        out[name] = _stats(lat)
    assert not client.write_register(0, 0, device_id=1).isError()    # give control back
    return out


def _crc16(data: bytes) -> bytes:
    crc = 0xFFFF
    for b in data:
        crc ^= b
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return crc.to_bytes(2, "little")


def _raw_rtu(path: str, n: int) -> dict:
    import select
    import tty

    body = bytes([1, 4, 0, 100, 0, 1])
    frame = body + _crc16(body)
    fd = os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    tty.setraw(fd)
    try:
        time.sleep(0.05)                        # inter-frame silence after the previous master
        lat = []
        for i in range(n + 20):
            t0 = time.perf_counter()
            os.write(fd, frame)
            got = b""
            while len(got) < 7:
                if not select.select([fd], [], [], 2.0)[0]:
                    raise RuntimeError("no answer from the rig over RTU")
                got += os.read(fd, 256)
            if i >= 20:
                lat.append(time.perf_counter() - t0)
            assert got[:3] == b"\x01\x04\x02" and got[-2:] == _crc16(got[:-2]), got.hex()
    finally:
        os.close(fd)
    return _stats(lat)


def bench_round_trip(quick: bool, tmp: Path) -> dict:
    from pymodbus import FramerType
    from pymodbus.client import ModbusSerialClient, ModbusTcpClient

    log("(b) round trips")
    cable = PtyPair(tmp)
    rig = RigProcess("--rig", "flutter", "--noise", "0.02", "--port", "0", "--serial", cable.b, cwd=REPO)
    try:
        port = int(rig.endpoints[0].rsplit(":", 1)[1])
        out = {"rig": "flutter, real time, noise 0.02", "client": "pymodbus sync client"}
        tcp = ModbusTcpClient("127.0.0.1", port=port, timeout=2)
        assert tcp.connect()
        out["tcp"] = _time_requests(tcp, 300 if quick else 1000)
        tcp.close()
        rtu = ModbusSerialClient(cable.a, framer=FramerType.RTU, baudrate=115200, timeout=2)
        assert rtu.connect()
        out["rtu_pty_115200"] = _time_requests(rtu, 150 if quick else 400)
        rtu.close()
        # the device's own share: a minimal raw RTU master (write the frame, wait for
        # the 7-byte answer) -- the rest of the pymodbus figure is the client's pacing
        out["rtu_pty_raw_master"] = {"read_1_register_fc4": _raw_rtu(cable.a, 300 if quick else 1000)}
        return out
    finally:
        rig.close()
        cable.close()


# ---- (c) ring buffer pull ---------------------------------------------------------------------------
def _pull(url: str, seconds: float) -> dict:
    from cbc_controller.client import RigClient

    c = RigClient(url, timeout=2.0, retries=1)
    c.connect()
    try:
        s0 = c.get("sample_seq")
        c.pull_ring()                                   # prime: start at the head
        records = gaps = requests = broken = 0
        last = None
        t0 = time.perf_counter()
        while time.perf_counter() - t0 < seconds:
            blk = c.pull_ring()
            n = len(blk.data["x"])
            records += n
            gaps += blk.gap
            requests += 2 + -(-n // (M.MAX_READ // M.RING_RECORD))
            sample = getattr(blk, "sample", None)      # absolute sample numbers, where the client gives them
            if sample is not None and n:
                if np.any(np.diff(sample) != 1) or (last is not None and blk.gap == 0 and sample[0] != last + 1):
                    broken += 1                         # a record overwritten while it was being read
                last = int(sample[-1])
        wall = time.perf_counter() - t0
        s1 = c.get("sample_seq")
        overruns = c.get("overruns")
    finally:
        c.close()
    return {"pulled_sps": round(records / wall), "rig_sps": round((s1 - s0) / wall), "gap_records": int(gaps),
            "discontinuities": broken, "requests_per_s": round(requests / wall), "rig_overruns": int(overruns)}


def _kept_up(r: dict) -> bool:
    """No record lost or torn, and the client pulled (nearly) as fast as the rig produced:
    a client slower than the rig only loses records once the ring (4096 records) is
    outrun, which a short trial would not show."""
    return r["gap_records"] == 0 and r["discontinuities"] == 0 and r["pulled_sps"] >= 0.95 * r["rig_sps"]


def bench_ring(quick: bool, tmp: Path) -> dict:
    scales = [0.25, 0.5, 1, 2, 4, 8, 16]
    seconds = 1.5 if quick else 3.0
    rate = 5000.0
    trials = []
    alive = {"tcp": True, "rtu": True}
    for k in scales:
        if not any(alive.values()):
            break
        log(f"(c) ring pull at time-scale {k}")
        cable = PtyPair(tmp)
        rig = RigProcess("--rig", "flutter", "--noise", "0.02", "--time-scale", str(k), "--port", "0",
                         "--serial", cable.b, cwd=REPO)
        try:
            time.sleep(0.3)
            trial = {"time_scale": k, "nominal_sps": int(k * rate)}
            for name, url in (("tcp", rig.endpoints[0]), ("rtu", f"serial://{cable.a}")):
                if alive[name]:
                    trial[name] = r = _pull(url, seconds)
                    r["kept_up"] = _kept_up(r)
                    alive[name] = r["kept_up"]          # a faster rig only leaves it further behind
        finally:
            rig.close()
            cable.close()
        trials.append(trial)
    best = {}
    for name in ("tcp", "rtu"):
        ok = [t for t in trials if name in t and t[name]["kept_up"]]
        first_loss = next((t["time_scale"] for t in trials if name in t and not t[name]["kept_up"]), None)
        best[name] = ({"max_gapless_sps": max(t[name]["rig_sps"] for t in ok),
                       "at_time_scale": max(ok, key=lambda t: t[name]["rig_sps"])["time_scale"],
                       "first_loss_at_time_scale": first_loss}
                      if ok else {"max_gapless_sps": 0, "first_loss_at_time_scale": first_loss})
    return {"rig": "flutter, 5000 Hz, noise 0.02, ring_decimation 1", "seconds_per_trial": seconds,
            "client": "RigClient.pull_ring in a loop (ring_head + records, 13 records per read)",
            "trials": trials, "best": best}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer repeats and shorter trials")
    args = ap.parse_args()
    if shutil.which("socat") is None:
        log("socat is needed for the RTU figures (apt-get install socat)")
        return 2
    t_start = time.perf_counter()
    import numba
    import pymodbus

    result = {
        "benchmark": "rig_benchmark", "version": rig_sim.__version__,
        "machine": {"nproc": os.cpu_count(), "usable_cpus": len(os.sched_getaffinity(0)),
                    "platform": platform.platform(), "python": platform.python_version(),
                    "cpu": _cpu_model(), "numpy": np.__version__, "numba": numba.__version__,
                    "pymodbus": pymodbus.__version__},
    }
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        result["realtime_factor"] = bench_realtime(args.quick, tmp)
        result["round_trip_ms"] = bench_round_trip(args.quick, tmp)
        result["ring_pull"] = bench_ring(args.quick, tmp)
    result["runtime_s"] = round(time.perf_counter() - t_start, 1)
    print(json.dumps(result, indent=1))
    return 0


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor()


if __name__ == "__main__":
    sys.exit(main())
