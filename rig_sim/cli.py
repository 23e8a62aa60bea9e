"""`rig-sim`: serve a virtual rig over Modbus, or print its register map."""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import signal
import sys

from . import __version__
from .device import register_map


class _Parser(argparse.ArgumentParser):
    def error(self, message):  # one line, exit 2 (argparse prints usage + error)
        self.exit(2, f"{self.prog}: error: {message}\n")


def _positive_float(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not math.isfinite(v) or v <= 0:
        raise argparse.ArgumentTypeError(f"{text!r} must be a positive number")
    return v


def _nonneg_float(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not math.isfinite(v) or v < 0:
        raise argparse.ArgumentTypeError(f"{text!r} must be a number >= 0")
    return v


def _port(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a port number") from None
    if not 0 <= v <= 65535:
        raise argparse.ArgumentTypeError(f"{text} is not in 0..65535")
    return v


def _unit(text: str) -> int:
    from .device.addressing import check_unit
    try:
        return check_unit(int(text))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a unit id in 1..247") from None


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="rig-sim", description="Virtual CBC lab rigs as Modbus devices.")
    p.add_argument("--version", action="version", version=f"rig-sim {__version__}")
    sub = p.add_subparsers(dest="command", required=True, parser_class=_Parser)

    s = sub.add_parser("serve", help="start a simulated rig (Modbus TCP and/or RTU serial)")
    s.add_argument("--rig", choices=["flutter", "oscillator"], required=True,
                   help="flutter: wind-tunnel aerofoil; oscillator: shaker-driven electrodynamic oscillator")
    s.add_argument("--host", default="127.0.0.1", help="TCP address to bind (default loopback)")
    s.add_argument("--port", type=_port, default=5020, help="TCP port (0: pick a free one; default 5020)")
    s.add_argument("--no-tcp", action="store_true", help="serve only on --serial")
    s.add_argument("--serial", metavar="PORT", help="also serve Modbus RTU on this serial port (e.g. a socat pty)")
    s.add_argument("--baud", type=int, default=115200, help="serial baud rate (default 115200)")
    s.add_argument("--unit", type=_unit, default=1, metavar="N",
                   help="Modbus unit id (slave address) 1..247 (default 1); see docs/protocol.md")
    clock = s.add_mutually_exclusive_group()
    clock.add_argument("--time-scale", type=_positive_float, default=1.0, metavar="K",
                       help="run K times faster than real time (default 1)")
    clock.add_argument("--lockstep", action="store_true",
                       help="advance only when the client writes the `advance` register")
    s.add_argument("--noise", type=_nonneg_float, default=0.0, metavar="SIGMA",
                   help="process-noise intensity (aerofoil: random pitch moment, N m/sqrt(Hz))")
    s.add_argument("--seed", type=int, default=0, help="seed of every random number the rig draws")
    s.add_argument("--effect", action="extend", nargs="+", default=[], metavar="NAME=VALUE",
                   help="undeclared physics, e.g. freeplay=0.01 (see docs/physics.md)")
    s.add_argument("--physics", action="extend", nargs="+", default=[], metavar="NAME=VALUE",
                   help="another configuration: physical parameters in place of the design "
                   "values, e.g. c1=0 c3=0 (the aerofoil's lag state off; docs/physics.md)")
    s.add_argument("--effect-plugin", metavar="FILE.py:FUNC",
                   help="user force FUNC(t, q, qdot, params) -> generalised forces")
    s.add_argument("--rate", type=_positive_float, help="board loop rate in Hz (default: the rig's)")
    s.add_argument("--adc-bits", type=int, default=16, help="ADC resolution (default 16)")
    s.add_argument("--latency-samples", type=int, default=0, help="actuator latency in samples")
    s.add_argument("--no-sensor-noise", action="store_true", help="ideal sensors (quantisation stays)")
    s.add_argument("--verbose", action="store_true", help="log protocol details")

    r = sub.add_parser("registers", help="print the register map")
    r.add_argument("--format", choices=["markdown", "json"], default="markdown")
    r.add_argument("--full", action="store_true", help="markdown: list every Fourier register")
    return p


def _serve(args) -> int:
    from .firmware.board import Board, RigOptions, SettingError
    from .physics.configuration import ConfigurationError
    from .physics.effects import EffectError
    from .device.server import Pacing, RigService, ServiceError, quiet_pymodbus

    quiet_pymodbus(args.verbose)
    options = RigOptions(kind=args.rig, sigma=args.noise, seed=args.seed, effects=args.effect,
                         physics=args.physics,
                         plugin=args.effect_plugin, sensor_noise=not args.no_sensor_noise,
                         adc_bits=args.adc_bits, latency_samples=args.latency_samples,
                         rate_hz=args.rate)
    pacing = Pacing(mode="lockstep" if args.lockstep else "realtime", time_scale=args.time_scale)
    try:
        board = Board(options)
        service = RigService(board, pacing, host=None if args.no_tcp else args.host,
                             port=args.port, serial=args.serial, baudrate=args.baud,
                             unit=args.unit)
        service.check()
    except (SettingError, EffectError, ConfigurationError, ServiceError) as exc:
        print(f"rig-sim: error: {exc}", file=sys.stderr)
        return 2
    board.advance(1)  # compile (or load the cached) kernel before announcing readiness
    board.__init__(options)  # and start from a clean board at t = 0

    async def main() -> int:
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, stop.set)
        try:
            await service.start()
        except ServiceError as exc:
            print(f"rig-sim: error: {exc}", file=sys.stderr)
            return 2
        where = []
        if service.host is not None:
            where.append(f"tcp://{service.host}:{service.port}")
        if service.serial is not None:
            where.append(f"serial://{service.serial}")
        clock = "lockstep" if args.lockstep else f"time-scale {args.time_scale:g}"
        print(json.dumps({"event": "serving", "rig": args.rig, "model": board.spec.model,
                          "endpoints": where, "unit": args.unit, "clock": clock, "noise": args.noise,
                          "seed": args.seed, "version": __version__}), flush=True)
        try:
            while not stop.is_set():
                if service.pacer is not None and service.pacer.error is not None:
                    raise service.pacer.error
                try:
                    await asyncio.wait_for(stop.wait(), timeout=0.5)
                except asyncio.TimeoutError:
                    pass
        finally:
            await service.stop()
        return 0

    return asyncio.run(main())


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    if args.command == "registers":
        if args.format == "json":
            sys.stdout.write(register_map.as_json() + "\n")
        else:
            sys.stdout.write(register_map.as_markdown(compact=not args.full))
        return 0
    return _serve(args)


if __name__ == "__main__":
    sys.exit(main())
