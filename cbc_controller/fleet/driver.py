"""The fleet's driver: submits the members as Ray tasks, writes what comes back, keeps the index.

The driver alone writes the output folder (the nodes share no files with it): each member's
campaign file as ``members/<id>/campaign.h5`` beside the ``campaign.toml`` it ran, and the
index (``index.json``, ``index.md``), rewritten whole after every member, one record per
member keyed by its id, so a member retried by Ray on another node is still counted once.
A rerun reads the index back: completed and failed members are done, an interrupted member
resumes from its file, the rest start.
"""

from __future__ import annotations

import dataclasses
import json
import os
import sys
import time
from datetime import datetime, timezone
from pathlib import Path

from .. import __version__
from .member import CAMPAIGN_FILE, CAMPAIGN_TOML, ControllerKilled, MemberResult, run_member
from .options import PLUGIN_FILE, FleetOptions, Member

INDEX_JSON = "index.json"
INDEX_MD = "index.md"
DONE = ("completed", "failed")          # a rerun leaves these alone
STOP_GRACE_S = 120.0                    # Ctrl-C: how long running members get to close files


class ClusterError(RuntimeError):
    """Ray is not installed (the optional extra ``cluster``), or its cluster cannot be
    joined (one line)."""


def connect(address: str | None) -> None:
    """Join the cluster at `address`, else at $RAY_ADDRESS (Ray's own convention), else
    start a local Ray on this machine."""
    try:
        import ray
    except ImportError:
        raise ClusterError("Ray is not installed: pip install -e \".[cluster]\"") from None
    if ray.is_initialized():
        return
    where = address or os.environ.get("RAY_ADDRESS")
    try:
        if where:
            ray.init(address=address, log_to_driver=False)
        else:
            ray.init(include_dashboard=False, log_to_driver=False)
    except (ConnectionError, RuntimeError, ValueError) as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise ClusterError(f"cannot {'join the Ray cluster at ' + where if where else 'start Ray'}"
                           f": {first}") from None


def _write_atomic(path: Path, data: bytes) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_bytes(data)
    os.replace(tmp, path)


def _pct(x) -> str:
    return "-" if x is None else f"{100 * x:.2f} %"


class FleetIndex:
    """The index: one record per member, in grid order, on disk after every change."""

    def __init__(self, options: FleetOptions, members: list[Member], out: Path):
        self.options, self.out = options, out
        old = {}
        if (out / INDEX_JSON).exists():
            old = {r["member"]: r for r in json.loads((out / INDEX_JSON).read_text())["members"]}
        self.records = {m.id: old.get(m.id) or {**m.record(), "status": "pending"}
                        for m in members}

    def status(self, member_id: str) -> str:
        return self.records[member_id]["status"]

    def resume_bytes(self, member: Member) -> bytes | None:
        f = self.out / "members" / member.id / CAMPAIGN_FILE
        return f.read_bytes() if self.status(member.id) == "interrupted" and f.exists() else None

    def put(self, member: Member, result: MemberResult) -> None:
        folder = self.out / "members" / member.id
        if result.file_bytes is not None:
            _write_atomic(folder / CAMPAIGN_FILE, result.file_bytes)
        status = result.status
        if status == "interrupted" and result.file_bytes is None:
            status = "pending"            # stopped before it logged anything: starts afresh
        self.records[member.id] = {
            **member.record(), "status": status, "error": result.error, **result.summary,
            "truth": result.truth, "wall_s": result.wall_s, "node": result.node,
            "file": f"members/{member.id}/{CAMPAIGN_FILE}" if (folder / CAMPAIGN_FILE).exists()
            else None, "finished": datetime.now(timezone.utc).isoformat()}
        self.write()

    def lost(self, member: Member, error: str) -> None:
        """Ray gave up on the task (retries spent): not done, a rerun tries again."""
        self.records[member.id] = {**self.records[member.id], "status": "lost", "error": error}
        self.write()

    def write(self) -> None:
        doc = {"fleet": self.options.name, "fleet_file": self.options.path,
               "fleet_toml": self.options.text, "version": __version__,
               "written": datetime.now(timezone.utc).isoformat(),
               "members": list(self.records.values())}
        _write_atomic(self.out / INDEX_JSON, json.dumps(doc, indent=1).encode())
        _write_atomic(self.out / INDEX_MD, self.table().encode())

    def counts(self) -> dict:
        out: dict[str, int] = {}
        for r in self.records.values():
            out[r["status"]] = out.get(r["status"], 0) + 1
        return out

    def table(self) -> str:
        head = ("| member | settings | status | points | stable / unstable | rig-s | wall s "
                "| truth: max error | error |\n|---|---|---|---|---|---|---|---|---|\n")
        rows = []
        for r in self.records.values():
            settings = _describe(r["settings"])
            truth = r.get("truth") or {}
            rows.append(f"| {r['member']} | {settings} | {r['status']} | {r.get('points', '-')} "
                        f"| {r.get('stable', '-')} / {r.get('unstable', '-')} "
                        f"| {r.get('rig_seconds', '-')} | {r.get('wall_s', '-')} "
                        f"| {_pct(truth.get('max_error')) if truth.get('known') else '-'} "
                        f"| {(r.get('error') or '').replace('|', '/')} |")
        return f"# Fleet {self.options.name}\n\n" + head + "\n".join(rows) + "\n"


def _describe(s: dict) -> str:
    """A member's settings in a few words: "noise 0.02, heave_cubic=5e+05, seed 3, --lockstep"."""
    words = [] if s["noise"] is None else [f"noise {s['noise']:g}"]
    words += [f"{k}={v:g}" for k, v in s["effects"].items()]
    if s["plugin"]:
        words.append(f"plugin {Path(s['plugin'].rsplit(':', 1)[0]).name}")
    if s["seed"] is not None:
        words.append(f"seed {s['seed']}")
    return ", ".join(words + [s["clock"]])


def _prepare(member: Member, out: Path) -> None:
    """The member's folder on the driver: the campaign file it runs (and its plugin)."""
    folder = out / "members" / member.id
    folder.mkdir(parents=True, exist_ok=True)
    (folder / CAMPAIGN_TOML).write_text(member.campaign_toml)
    if member.plugin_source is not None:
        (folder / PLUGIN_FILE).write_bytes(member.plugin_source)


def _control():
    """A tiny actor on the driver's node whose stop flag running members poll: Ctrl-C on the
    driver sets it, and each member then interrupts its controller, which closes its file
    cleanly."""
    import ray
    from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

    @ray.remote(num_cpus=0, max_restarts=-1)
    class FleetControl:
        def __init__(self):
            self.stopped = False

        def stop(self):
            self.stopped = True

        def is_set(self):
            return self.stopped

    here = ray.get_runtime_context().get_node_id()
    return FleetControl.options(
        scheduling_strategy=NodeAffinitySchedulingStrategy(here, soft=True)).remote()


def _member_task(member: Member, resume: bytes | None, control) -> MemberResult:
    import ray
    node = f"{ray.util.get_node_ip_address()}/{ray.get_runtime_context().get_node_id()[:8]}"

    def stop_requested() -> bool:
        try:
            return bool(ray.get(control.is_set.remote(), timeout=5))
        except Exception:            # the control actor unreachable: keep running
            return False
    return dataclasses.replace(run_member(member, resume, stop_requested), node=node)


class Progress:
    """One line per member that ends, with the fleet's counts, elapsed time and an ETA."""

    def __init__(self, total: int, stream):
        self.total, self.stream, self.t0, self.done = max(total, 1), stream, time.time(), 0

    def __call__(self, record: dict, counts: dict) -> None:
        self.done += 1
        el = time.time() - self.t0
        eta = el / self.done * (self.total - self.done)
        truth = record.get("truth") or {}
        what = (f"{record.get('points', 0)} points ({record.get('stable', 0)} stable, "
                f"{record.get('unstable', 0)} unstable)")
        if truth.get("known") and truth.get("max_error") is not None:
            what += f", truth within {_pct(truth['max_error'])}"
        if record.get("error"):
            what += f": {record['error']}"
        tally = ", ".join(f"{n} {s}" for s, n in sorted(counts.items()))
        self.stream.write(f"[{self.done}/{self.total}] {record['member']}: {record['status']}, "
                          f"{what}, {record.get('wall_s', 0):.0f} s on {record.get('node')} "
                          f"| fleet: {tally} | elapsed {el:.0f} s, ETA {eta:.0f} s\n")
        self.stream.flush()


def run_fleet(options: FleetOptions, out: str | Path, address: str | None = None,
              stream=sys.stderr) -> int:
    """Run every member not yet done; returns the exit status (0: all completed, 1: some
    failed or lost, 130: interrupted by Ctrl-C)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    members = options.members()
    index = FleetIndex(options, members, out)
    todo = [m for m in members if index.status(m.id) not in DONE]
    resumed = sum(index.status(m.id) == "interrupted" for m in todo)
    stream.write(f"fleet {options.name}: {len(members)} members, {len(members) - len(todo)} "
                 f"done, {len(todo)} to run" + (f" ({resumed} resumed)" if resumed else "") + "\n")
    index.write()
    if not todo:
        return _exit_status(index)
    connect(address)
    import ray
    control = _control()
    # SPREAD: a queued member goes to any free node (the default packs the driver's node first)
    task = ray.remote(num_cpus=options.cpus_per_member, max_retries=options.retries,
                      retry_exceptions=[ControllerKilled],
                      scheduling_strategy="SPREAD")(_member_task)
    pending = {}
    for m in todo:
        _prepare(m, out)
        pending[task.remote(m, index.resume_bytes(m), control)] = m
    progress = Progress(len(todo), stream)
    interrupted, deadline = False, None
    while pending:
        try:
            ready, _ = ray.wait(list(pending), num_returns=1, timeout=1.0)
            for ref in ready:
                m = pending[ref]             # dropped once written: a Ctrl-C here loses nothing
                try:
                    index.put(m, ray.get(ref))
                except ray.exceptions.RayError as exc:
                    index.lost(m, f"{type(exc).__name__}: {str(exc).splitlines()[0]}")
                del pending[ref]
                progress(index.records[m.id], index.counts())
            if deadline is not None and time.time() > deadline:
                break
        except KeyboardInterrupt:
            if interrupted:
                break
            interrupted, deadline = True, time.time() + STOP_GRACE_S
            control.stop.remote()
            stream.write(f"\nfleet: stopping; {len(pending)} running members close their "
                         "files (Ctrl-C again to leave them)\n")
    for ref in pending:
        ray.cancel(ref, force=True)
    index.write()
    counts = index.counts()
    stream.write("fleet " + ("interrupted" if interrupted else "done") + ": "
                 + ", ".join(f"{n} {s}" for s, n in sorted(counts.items()))
                 + f"; index: {out / INDEX_JSON}\n")
    return 130 if interrupted else _exit_status(index)


def _exit_status(index: FleetIndex) -> int:
    return 0 if all(r["status"] == "completed" for r in index.records.values()) else 1
