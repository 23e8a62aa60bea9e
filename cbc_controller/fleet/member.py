"""One fleet member, run wherever Ray puts it: `cbc-campaign run` as a subprocess in a scratch
folder of that node, its embedded rig on the node's own loopback. Nothing is assumed shared:
the member's campaign file (and plugin) travel with the task, and the campaign file it writes
travels back to the driver as bytes, with a summary.
"""

from __future__ import annotations

import ctypes
import platform
import signal
import subprocess
import sys
import tempfile
import time
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from .options import PLUGIN_FILE, Member

CAMPAIGN_FILE = "campaign.h5"
CAMPAIGN_TOML = "campaign.toml"
POLL_S = 0.5
# signals that end a controller from outside (its node lost, the OOM killer, an operator):
# the machine's trouble, not the member's, so the member is run again
OUTSIDE_KILLS = frozenset({signal.SIGKILL, signal.SIGTERM, signal.SIGHUP})


class ControllerKilled(RuntimeError):
    """A member's controller ended by a signal nobody in the fleet sent. Raised, not returned
    as "failed": the worker can outlive its node for a moment (a lost node's raylet and its
    workers do not die at one instant), and a result it returned then would record the node's
    loss as the member's failure; the driver's task retries on this error as on a dead
    worker."""


@dataclass(frozen=True)
class MemberResult:
    """What comes back to the driver. status: "completed", "interrupted" (stopped on the
    driver's request; resumable from `file_bytes`) or "failed" (with `error`)."""
    member: str
    status: str
    error: str | None
    summary: dict
    truth: dict | None
    wall_s: float
    node: str
    file_bytes: bytes | None = field(default=None, repr=False)


def _controller_setup() -> None:
    """In the controller, before it starts: Ctrl-C works again (a Ray worker may ignore or
    block SIGINT, and both survive exec), and on Linux it gets SIGTERM when the worker running
    it dies (a lost node)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)   # PR_SET_PDEATHSIG
    except OSError:
        pass


def campaign_summary(path: str) -> tuple[dict, list[dict]]:
    """Points, stability counts, rig-seconds (summed over the file's runs) and the last
    stop reason of a campaign file; and its points."""
    from ..log import read_campaign
    camp = read_campaign(path)
    ok = [p for p in camp.points if p.get("status", "ok") == "ok"]
    per_run: dict[int, float] = {}
    for p in camp.points:
        t = p.get("rig_time")
        if isinstance(t, (int, float)) and t == t:
            per_run[p.get("run", 0)] = max(per_run.get(p.get("run", 0), 0.0), float(t))
    return {"points": len(camp.points), "stable": sum(bool(p["stable"]) for p in ok),
            "unstable": sum(not p["stable"] for p in ok),
            "failed_points": len(camp.points) - len(ok),
            "rig_seconds": round(sum(per_run.values()), 3), "runs": len(camp.runs),
            "stop_reason": camp.runs[-1].get("stop_reason") if camp.runs else None}, camp.points


def _last_line(text: str, returncode: int) -> str:
    lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
    if lines:
        return lines[-1]
    if returncode < 0:
        return f"the controller died of {signal.Signals(-returncode).name}"
    return f"the controller exited with status {returncode} and no output"


def run_member(member: Member, resume: bytes | None = None,
               stop_requested: Callable[[], bool] = lambda: False) -> MemberResult:
    """Run one member to its end (or until `stop_requested()` turns true: the controller is
    then interrupted as by Ctrl-C and closes its file cleanly). `resume`: the bytes of the
    member's unfinished campaign file, continued with `--resume`."""
    node = platform.node()
    if stop_requested():                  # stopped while queued: it never started
        return MemberResult(member.id, "interrupted", None, {}, None, 0.0, node)
    with tempfile.TemporaryDirectory(prefix=f"fleet-{member.id}-") as tmp:
        work = Path(tmp)
        (work / CAMPAIGN_TOML).write_text(member.campaign_toml)
        if member.plugin_source is not None:
            (work / PLUGIN_FILE).write_bytes(member.plugin_source)
        out = work / CAMPAIGN_FILE
        if resume is not None:
            out.write_bytes(resume)
            args = ["--resume", str(out)]
        else:
            args = [str(work / CAMPAIGN_TOML), "--out", str(out)]
        cmd = [sys.executable, "-m", "cbc_controller.cli", "run", *args, *member.clock_args,
               "--quiet"]
        t0 = time.monotonic()
        proc = subprocess.Popen(cmd, cwd=work, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                text=True, preexec_fn=_controller_setup)
        stopped = False
        while True:
            try:
                _, err = proc.communicate(timeout=POLL_S)
                break
            except subprocess.TimeoutExpired:
                if not stopped and stop_requested():
                    proc.send_signal(signal.SIGINT)
                    stopped = True
        wall = time.monotonic() - t0
        if not stopped and -proc.returncode in OUTSIDE_KILLS:
            raise ControllerKilled(f"{member.id}: its controller was killed by "
                                   f"{signal.Signals(-proc.returncode).name}")
        summary, points, data = {}, [], None
        if out.exists():
            try:
                summary, points = campaign_summary(str(out))
                data = out.read_bytes()
            except Exception as exc:          # a file the controller never got to write
                summary = {"unreadable": f"{type(exc).__name__}: {exc}"}
        reason = summary.get("stop_reason")
        if proc.returncode == 0 and reason == "completed":
            status, error = "completed", None
        elif stopped:
            status, error = "interrupted", None
        else:
            status = "failed"
            error = (reason if reason and reason != "completed"
                     else _last_line(err, proc.returncode))
        truth = None
        if points and status != "interrupted":
            from .truth import truth_agreement      # numba: only where a member ran
            rig_table = tomllib.loads(member.campaign_toml).get("rig", {})
            truth = truth_agreement(member.rig, rig_table, points)
        return MemberResult(member.id, status, error, summary, truth, round(wall, 3), node,
                            data if status != "failed" or data else None)
