"""`cbc-campaign`: run a CBC campaign against a rig, and look at its file."""

from __future__ import annotations

import argparse
import json
import math
import os
import signal
import subprocess
import sys
import time
from datetime import datetime, timezone
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


# ------------------------------------------------------------------ embedded rig --------
def _die_with_parent() -> None:
    """Linux: the embedded rig gets SIGTERM when the controller dies, even by SIGKILL."""
    try:
        import ctypes
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)   # PR_SET_PDEATHSIG
    except OSError:
        pass


class EmbeddedRig:
    """A `rig-sim serve` process on a free loopback port, stopped at the end."""

    def __init__(self, config: dict, time_scale: float | None, lockstep: bool):
        rig = config["rig"]
        args = [sys.executable, "-m", "rig_sim.cli", "serve", "--rig", config["campaign"]["rig"],
                "--host", "127.0.0.1", "--port", "0",
                "--seed", str(rig.get("seed", config["campaign"].get("seed", 0))),
                "--noise", str(rig.get("noise", 0.0))]
        if lockstep or (time_scale is None and rig.get("lockstep", False)):
            args.append("--lockstep")
        else:
            scale = time_scale if time_scale is not None else rig.get("time_scale", 20.0)
            args += ["--time-scale", str(scale)]
        if rig.get("effects"):
            args += ["--effect", *rig["effects"]]
        if rig.get("plugin"):
            args += ["--effect-plugin", rig["plugin"]]
        self.args = args
        self.proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                     text=True, start_new_session=True,
                                     preexec_fn=_die_with_parent)
        line = self.proc.stdout.readline()
        if not line:
            err = self.proc.stderr.read().strip().splitlines()
            raise RuntimeError(f"the embedded rig did not start: {err[-1] if err else 'no output'}")
        info = json.loads(line)
        self.url = info["endpoints"][0]

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.proc.kill()


# ------------------------------------------------------------------ progress ------------
class Progress:
    """Points done, the latest point, rig time and an ETA on one terminal line."""

    def __init__(self, total_tasks: int, stream=sys.stderr):
        self.total = max(total_tasks, 1)
        self.stream = stream
        self.t0 = time.time()
        self.points = 0
        self.tasks_done: set = set()
        self.stable = self.unstable = 0

    def __call__(self, kind: str, doc: dict) -> None:
        if kind == "point":
            self.points += 1
            self.stable += bool(doc["stable"])
            self.unstable += not doc["stable"]
            self.tasks_done.add(doc["key"].split("/")[0])
            el = time.time() - self.t0
            frac = len(self.tasks_done) / self.total
            eta = el / frac - el if frac > 0 else float("nan")
            res = doc["extra"].get("final_error")     # the aerofoil's root residual
            self.stream.write(
                f"\r[{self.points} points: {self.stable} stable, {self.unstable} unstable] "
                f"{doc['key']}: A = {doc['amplitude'] * 1e3:.3f} mm, "
                f"{'stable' if doc['stable'] else 'unstable'}"
                + (f", residual {res:.1e} m" if res is not None else "")
                + f" | elapsed {el:.0f} s, ETA {eta:.0f} s   ")
            self.stream.flush()
        elif kind in ("fault", "link", "note"):
            self.stream.write(f"\n{kind}: {json.dumps(doc, default=str)}\n")
            self.stream.flush()
        elif kind == "stop":
            self.stream.write(f"\ncampaign {doc['reason']}: {self.points} points "
                              f"({self.stable} stable, {self.unstable} unstable) in "
                              f"{time.time() - self.t0:.0f} s\n")
            self.stream.flush()


# ------------------------------------------------------------------ run ----------------
def _versions() -> dict:
    from importlib.metadata import PackageNotFoundError, version
    out = {"virtual-cbc-lab": __version__}
    for pkg in ("numpy", "pymodbus", "h5py"):
        try:
            out[pkg] = version(pkg)
        except PackageNotFoundError:
            pass
    return out


def _run(args) -> int:
    from .campaign import CampaignError, load_campaign, validate
    from .client import RigClient, RigError
    from .engine import CampaignAbort, Engine, LoopOptions
    from .log import CampaignFileError, CampaignWriter, read_campaign
    from .messages import PlanContext
    from .plans import plan_for

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

    loop = LoopOptions(**{k: v for k, v in config["loop"].items() if k in LoopOptions.__dataclass_fields__})
    rig_url = args.rig
    embedded = None
    try:
        if rig_url is None:
            embedded = EmbeddedRig(config, args.time_scale, args.lockstep)
            rig_url = embedded.url
        try:
            client = RigClient(rig_url, timeout=2.0, retries=1)
        except ValueError as exc:
            return _fail(str(exc))
        subscribers = []
        if not args.quiet:
            tasks = config["parameter"]["values"] if config["campaign"]["rig"] == "flutter" \
                else config["frequencies"]
            subscribers.append(Progress(len(tasks)))
        out.parent.mkdir(parents=True, exist_ok=True)
        writer = CampaignWriter(str(out), resume=bool(args.resume))
        engine = Engine(client, loop, [writer, *subscribers])
        try:
            identity = engine.start()
        except RigError as exc:
            writer.close() if hasattr(writer, "close") else None
            if not args.resume and out.exists():
                out.unlink()
            return _fail(f"the rig at {rig_url} does not answer ({exc})", 1)
        kind = "flutter" if identity["rig_kind"] == 0 else "oscillator"
        if kind != config["campaign"]["rig"]:
            engine.close()
            return _fail(f"the campaign is for the {config['campaign']['rig']} rig but {rig_url} "
                         f"is a {kind} rig ({identity['model']})")
        engine.emit("start", {
            "campaign": config, "campaign_toml": text, "identity": identity,
            "versions": _versions(), "rig_url": rig_url,
            "started": datetime.now(timezone.utc).isoformat(), "command": sys.argv,
            "seed": config["campaign"].get("seed", 0)})
        reason = "completed"
        try:
            reason = engine.run(plan_for(config), PlanContext(config, identity, done, prev_points))
        except CampaignAbort as exc:
            reason = f"aborted: {exc}"
        except KeyboardInterrupt:
            reason = "interrupted"
        finally:
            engine.emit("stop", {"reason": reason, "ended": datetime.now(timezone.utc).isoformat(),
                                 "loop": engine.stats.summary()})
            if hasattr(writer, "close"):
                writer.close()
            engine.close()
        print(json.dumps({"file": str(out), "reason": reason}))
        return 0 if reason == "completed" else 1
    except RuntimeError as exc:
        return _fail(str(exc), 1)
    finally:
        if embedded is not None:
            embedded.stop()


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
