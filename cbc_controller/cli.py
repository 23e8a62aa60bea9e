"""`cbc-campaign`: run a CBC campaign against a rig, and look at its file."""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
from pathlib import Path

from . import __version__


def _positive_float(text: str) -> float:
    """argparse type: a finite number > 0 (a time scale of 0 is not "the default")."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not math.isfinite(value) or value <= 0:
        raise argparse.ArgumentTypeError(f"{text!r} must be a positive number")
    return value


class _Parser(argparse.ArgumentParser):
    def error(self, message):          # one line, exit 2
        self.exit(2, f"{self.prog}: error: {message}\n")


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="cbc-campaign", description="Control-based continuation campaigns over Modbus.")
    p.add_argument("--version", action="version", version=f"cbc-campaign {__version__}")
    sub = p.add_subparsers(dest="command", required=True, parser_class=_Parser)
    r = sub.add_parser("run", help="run a campaign (TOML) and log it to HDF5")
    r.add_argument("campaign", nargs="?", help="campaign file (TOML); not needed with --resume")
    r.add_argument("--rig", metavar="URL",
                   help="tcp://HOST:PORT, serial://PORT or socket://HOST:PORT; default: start a "
                        "local rig service on a free loopback port")
    r.add_argument("--out", metavar="FILE.h5", help="campaign file to write (default: runs/<name>.h5)")
    r.add_argument("--resume", metavar="FILE.h5", help="continue a campaign that was interrupted")
    clock = r.add_mutually_exclusive_group()
    clock.add_argument("--time-scale", type=_positive_float, metavar="K",
                       help="embedded rig: K x real time (K > 0)")
    clock.add_argument("--lockstep", action="store_true", help="embedded rig: lockstep (fastest)")
    r.add_argument("--quiet", action="store_true", help="no progress on the terminal")
    idn = sub.add_parser("identify", help="read a rig's device identification (exit 0 if it "
                         "answers: a health check)")
    idn.add_argument("rig", metavar="URL", help="tcp://HOST:PORT, serial://PORT or "
                     "socket://HOST:PORT")
    idn.add_argument("--timeout", type=float, default=2.0, metavar="S",
                     help="seconds to wait for an answer (default 2)")
    v = sub.add_parser("validate", help="check a campaign file without touching a rig")
    v.add_argument("campaign")
    i = sub.add_parser("inspect", help="summarise a campaign file")
    i.add_argument("file")
    i.add_argument("--json", action="store_true", help="the points as JSON, for scripts")
    pl = sub.add_parser("plot", help="bifurcation diagram of a campaign file (PNG)")
    pl.add_argument("file")
    pl.add_argument("--out", metavar="FILE.png", help="default: next to the campaign file")
    return p


def _fail(message: str, code: int = 2) -> int:
    print(f"cbc-campaign: error: {message}", file=sys.stderr)
    return code


def _run(args) -> int:
    from .campaign import CampaignError, load_campaign, validate
    from .log import CampaignFileError, read_campaign
    from .run import RunError, run_campaign

    # 1. everything the user gave is checked before anything touches a rig
    try:
        if args.resume:
            previous = read_campaign(args.resume)
            text = previous.metadata.get("campaign_toml")
            if not text:
                return _fail(f"{args.resume}: holds no campaign description to resume")
            import tomllib
            config = validate(tomllib.loads(text), args.resume)
            out = Path(args.resume)
            done = {p["key"] for p in previous.points}
            prev_points = previous.points
        else:
            if not args.campaign:
                return _fail("give a campaign file (or --resume FILE.h5)")
            config, text = load_campaign(args.campaign)
            name = config["campaign"].get("name") or Path(args.campaign).stem
            out = Path(args.out or f"runs/{name}.h5")
            if out.exists():
                return _fail(f"{out} exists: use --resume {out} to continue it, or another --out")
            done, prev_points = set(), []
    except (CampaignError, CampaignFileError) as exc:
        return _fail(str(exc))
    # 2. the run
    try:
        reason = run_campaign(config, text, out, rig_url=args.rig, time_scale=args.time_scale,
                              lockstep=args.lockstep, resume=bool(args.resume), done=done,
                              previous=prev_points, progress=not args.quiet)
    except RunError as exc:
        return _fail(str(exc), exc.code)
    print(json.dumps({"file": str(out), "reason": reason}))
    return 0 if reason == "completed" else 1


def _identify(args) -> int:
    import logging

    from .client import RigClient, RigError
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)   # our one line says it all
    if not args.timeout > 0:
        return _fail(f"--timeout must be positive, not {args.timeout}")
    try:
        client = RigClient(args.rig, timeout=args.timeout, retries=0)
    except ValueError as exc:
        return _fail(str(exc))
    try:
        identity = client.connect()
    except RigError as exc:
        return _fail(f"the rig at {args.rig} does not answer ({exc})", 1)
    finally:
        client.close()
    print(json.dumps(identity))
    return 0


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    if args.command == "run":
        return _run(args)
    if args.command == "identify":
        return _identify(args)
    if args.command == "validate":
        from .campaign import CampaignError, load_campaign
        try:
            cfg, _ = load_campaign(args.campaign)
        except CampaignError as exc:
            return _fail(str(exc))
        print(f"{args.campaign}: ok ({cfg['campaign']['rig']} campaign)")
        return 0
    from .log import CampaignFileError, read_campaign
    from .report import inspect_json, inspect_text, plot_campaign
    try:
        camp = read_campaign(args.file)
    except CampaignFileError as exc:
        return _fail(str(exc))
    if args.command == "inspect":
        if args.json:
            print(json.dumps(inspect_json(camp), indent=1))
        else:
            print(inspect_text(camp))
        return 0
    png = args.out or os.path.splitext(args.file)[0] + ".png"
    plot_campaign(camp, png)
    print(png)
    return 0


def _entry() -> int:
    try:
        return main()
    except BrokenPipeError:          # output piped into `head` and the like
        try:
            sys.stdout = open(os.devnull, "w")
        except OSError:
            pass
        return 0


if __name__ == "__main__":
    sys.exit(_entry())
