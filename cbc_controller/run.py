"""Running a campaign: the embedded rig, the plan, the engine and its subscribers (the HDF5
writer, the progress line), wired together between a start and a stop document.

`run_campaign` is the library call under `cbc-campaign run`; the CLI only parses, reads the
campaign (or the file to resume) and prints.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from datetime import datetime, timezone
from pathlib import Path

from . import __version__
from .client import RigClient, RigError
from .engine import CampaignAbort, Engine, LoopOptions, link_for
from .log import CampaignWriter
from .messages import PlanContext
from .plans import plan_for


class RunError(RuntimeError):
    """The campaign could not run (one line) and the exit status that says so."""

    def __init__(self, message: str, code: int = 1):
        super().__init__(message)
        self.code = code


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
        self.lockstep = lockstep or (time_scale is None and rig.get("lockstep", False))
        if self.lockstep:
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
def versions() -> dict:
    from importlib.metadata import PackageNotFoundError, version
    out = {"virtual-cbc-lab": __version__}
    for pkg in ("numpy", "pymodbus", "h5py"):
        try:
            out[pkg] = version(pkg)
        except PackageNotFoundError:
            pass
    return out


def run_campaign(config: dict, text: str, out: Path, *, rig_url: str | None = None,
                 time_scale: float | None = None, lockstep: bool = False, resume: bool = False,
                 done=(), previous=(), progress: bool = True) -> str:
    """Run a validated campaign into `out` (a new file, or the one resumed, whose point keys
    are `done` and summaries `previous`) against the rig at `rig_url`, or a rig service
    started here; returns why it ended ("completed", "interrupted", "aborted: ...").
    RunError for a rig that cannot be reached or is of the other kind."""
    loop = LoopOptions(**{k: v for k, v in config["loop"].items()
                          if k in LoopOptions.__dataclass_fields__})
    embedded = None
    try:
        if rig_url is None:
            embedded = EmbeddedRig(config, time_scale, lockstep)
            rig_url = embedded.url
        try:
            # an embedded rig's clock is known before its first answer; another's, after it
            client = RigClient(rig_url, *link_for(loop, embedded is not None and embedded.lockstep))
        except ValueError as exc:
            raise RunError(str(exc), 2) from None
        subscribers = []
        if progress:
            tasks = config["parameter"]["values"] if config["campaign"]["rig"] == "flutter" \
                else config["frequencies"]
            subscribers.append(Progress(len(tasks)))
        out.parent.mkdir(parents=True, exist_ok=True)
        writer = CampaignWriter(str(out), resume=resume)
        engine = Engine(client, loop, [writer, *subscribers])
        try:
            identity = engine.start()
        except RigError as exc:
            writer.close()
            if not resume and out.exists():
                out.unlink()
            raise RunError(f"the rig at {rig_url} does not answer ({exc})", 1) from None
        kind = "flutter" if identity["rig_kind"] == 0 else "oscillator"
        if kind != config["campaign"]["rig"]:
            engine.close()
            raise RunError(f"the campaign is for the {config['campaign']['rig']} rig but "
                           f"{rig_url} is a {kind} rig ({identity['model']})", 2)
        engine.emit("start", {
            "campaign": config, "campaign_toml": text, "identity": identity,
            "versions": versions(), "rig_url": rig_url,
            "started": datetime.now(timezone.utc).isoformat(), "command": sys.argv,
            "seed": config["campaign"].get("seed", 0)})
        reason = "completed"
        try:
            reason = engine.run(plan_for(config),
                                PlanContext(config, identity, set(done), list(previous)))
        except CampaignAbort as exc:
            reason = f"aborted: {exc}"
        except KeyboardInterrupt:
            reason = "interrupted"
        finally:
            engine.emit("stop", {"reason": reason, "ended": datetime.now(timezone.utc).isoformat(),
                                 "loop": engine.stats.summary()})
            writer.close()
            engine.close()
        return reason
    except RunError:
        raise
    except RuntimeError as exc:          # the embedded rig did not start
        raise RunError(str(exc), 1) from None
    finally:
        if embedded is not None:
            embedded.stop()
