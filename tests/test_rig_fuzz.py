"""Robustness: the rig under a storm of random and mutated Modbus frames. The storm
and its checks are in tests/rig_fuzzing.py, the frames and the datasheet model in
tests/fuzz_frames.py; the full-size run (100,000 TCP and 10,000 RTU frames) is
benchmarks/fuzz_benchmark.py.

The rigs run with --verbose, their log in a file: a request that raised inside the
server would leave a traceback there, and none may."""

from __future__ import annotations

from tests.fuzz_frames import Fuzzer, crc16
from tests.rig_fuzzing import SEED, run_rtu, run_tcp

TCP_FRAMES = 10_000
RTU_FRAMES = 5_000


def test_crc_reference_value():
    # the worked example of the Modbus serial-line guide: 01 03 00 00 00 01 -> 84 0A
    assert crc16(bytes.fromhex("010300000001")) == bytes.fromhex("840A")


def _no_tracebacks(rig):
    rig.stop()
    log = rig.stderr()
    assert log.count("Traceback") == 0, f"{log.count('Traceback')} tracebacks inside the rig"


def test_fuzz_tcp(rig_process, tmp_path):
    rig = rig_process("--rig", "flutter", "--lockstep", "--verbose", stderr_file=tmp_path / "rig.log")
    out = run_tcp(rig, TCP_FRAMES, SEED, n_after=100)
    print(f"\nTCP: {out}")
    assert out["answers_checked"] > 0.5 * out["frames"]
    for kind in Fuzzer.KINDS + ["tcp_truncated", "tcp_overlong", "tcp_bad_length", "tcp_bad_protocol",
                                "tcp_random", "tcp_no_function", "unit_other"]:
        assert out["by_kind"].get(kind, 0) >= 20, kind
    for code in ("01", "02", "03", "0B"):
        assert out["exception_codes"].get(code, 0) >= 20, code
    _no_tracebacks(rig)


def test_fuzz_rtu(rig_process, pty_pair, tmp_path):
    rig = rig_process("--rig", "oscillator", "--lockstep", "--no-tcp", "--serial", pty_pair.b, "--verbose",
                      stderr_file=tmp_path / "rig.log")
    out = run_rtu(rig, pty_pair, RTU_FRAMES, SEED + 1, n_after=50)
    print(f"\nRTU: {out}")
    n = out["frames"]
    # the storm must have exercised the answer path (how many answers a partial
    # frame swallows depends on when the device reads the pty: loose bounds)
    assert out["answers_checked"] > 0.25 * n
    assert out["relaxed_after_partial_frame"] < 0.2 * n
    assert out["frames_resent"] < 0.02 * n
    for kind in Fuzzer.KINDS:
        assert out["by_kind"].get(kind, 0) >= 25, kind
    for name in ("as_is", "bad_crc", "truncated", "overlong", "garbled", "random_bytes", "broadcast",
                 "other_unit"):
        assert out["on_the_line"].get(name, 0) >= 100, name
    _no_tracebacks(rig)
