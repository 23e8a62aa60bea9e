"""`cbc-demo`: the whole lab end to end, as three processes, into one run folder.

    python3 -m cbc_controller.demo [--system flutter|oscillator] [--out DIR] ...

1. the rig:     `rig-sim serve` on a free loopback port, time-scaled, as its own process;
2. a campaign:  `cbc-campaign run` against it over Modbus TCP, logging to DIR/campaign.h5;
3. the fit:     `ude-fit pipeline` on that file: mechanistic model, UDE, the missing physics
                found and added, into DIR/analysis/;

then DIR/report.md and DIR/metrics.json with the headline figures. These are the three
commands that docker-compose.yml runs as services. Ctrl-C stops the child that is running
and the rig; what was logged stays, and the same command again resumes the campaign.

The controller may not import `rig_sim` beyond the register map (and the effect catalogue,
to check a campaign's embedded rig), so the rig and the fit are reached only through their
command lines.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import signal
import subprocess
import sys
import time
from datetime import datetime, timezone
from importlib import resources
from pathlib import Path

from . import __version__

SYSTEMS = ("flutter", "oscillator")
# The aerofoil's UDE is asked to stay regular away from the measured orbits: without this a
# network that matches every point can still snake between them and move the Hopf point
# (see `ude-fit fit --help`; measured in docs/benchmarks.md). These penalties were set for
# the plain network, which the demo keeps: with the rest-free default they are redundant
# (the equilibrium penalty) and, on the demo's interrupted 3-point campaign, its one start
# diverged (2026-11-26).
SMOOTH_UDE = {"flutter": ("--no-rest-free", "--constraint-rounds", "0",
                          "--equilibrium-penalty", "1", "--smoothness-penalty", "1e-4",
                          "--param-scale", "4")}
EXIT_INTERRUPTED = 130


class _Parser(argparse.ArgumentParser):
    def error(self, message):          # one line, exit 2
        self.exit(2, f"{self.prog}: error: {message}\n")


def _number(name: str, kind=float, allow_zero: bool = False):
    """An argparse type: a finite number above zero (or at least zero)."""
    def conv(text):
        try:
            v = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{name} must be a number, not {text!r}") from None
        if not (v >= 0 if allow_zero else v > 0) or v == float("inf"):
            raise argparse.ArgumentTypeError(
                f"{name} must be finite and {'not negative' if allow_zero else 'positive'}, "
                f"not {text!r}")
        return v
    return conv


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="cbc-demo", description="The lab end to end: start a rig, run a CBC "
                "campaign against it over Modbus, fit and explain the data, report.")
    p.add_argument("--version", action="version", version=f"cbc-demo {__version__}")
    p.add_argument("--system", choices=SYSTEMS, default="flutter",
                   help="the wind-tunnel aerofoil (default) or the forced oscillator")
    p.add_argument("--out", metavar="DIR",
                   help="run folder (default runs/demo-SYSTEM); the same folder again resumes")
    p.add_argument("--campaign", metavar="FILE.toml",
                   help="campaign file instead of the built-in demo campaign")
    p.add_argument("--time-scale", type=_number("--time-scale"), default=20.0, metavar="K",
                   help="the rig runs K x faster than real time (default 20)")
    p.add_argument("--noise", type=_number("--noise", allow_zero=True), default=0.0, metavar="SIGMA",
                   help="the rig's process noise (default 0)")
    p.add_argument("--effect", nargs="+", default=[], metavar="NAME=VALUE",
                   help="hidden physics to plant in the rig (see `rig-sim serve --help`)")
    p.add_argument("--seed", type=int, default=1, help="the rig's and the fit's seed (default 1)")
    p.add_argument("--starts", type=_number("--starts", int), default=3,
                   help="UDE random starts (default 3)")
    return p


def _fail(message: str, code: int = 2) -> int:
    print(f"cbc-demo: error: {message}", file=sys.stderr)
    return code


def _child_setup() -> None:
    """In each child: SIGINT back to its default (a shell's `&` ignores it, and an ignored
    signal stays ignored across exec), so the demo can always interrupt it; and, on Linux,
    SIGTERM when the demo dies, even by SIGKILL."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    try:
        import ctypes
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)   # PR_SET_PDEATHSIG
    except OSError:
        pass


def _say(text: str) -> None:
    print(f"\n== {text}", file=sys.stderr, flush=True)


class _Child:
    """A step of the demo as its own process in its own session: a Ctrl-C on the terminal
    reaches the demo only, which then stops the children in order (the campaign first, so
    that it closes its file; the rig last)."""

    def __init__(self, args: list[str], **kw):
        self.args = args
        self.proc = subprocess.Popen(args, start_new_session=True,
                                     preexec_fn=_child_setup, **kw)

    def wait(self) -> int:
        try:
            return self.proc.wait()
        except KeyboardInterrupt:
            self.interrupt()
            raise

    def interrupt(self, grace: float = 60.0) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(timeout=grace)
            except subprocess.TimeoutExpired:
                self.stop()

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=15)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()


def _shown(args: list[str]) -> str:
    """A child's command line as a user would type it."""
    tools = {"rig_sim.cli": "rig-sim", "cbc_controller.cli": "cbc-campaign",
             "ude_fit.cli": "ude-fit"}
    if len(args) > 2 and args[1] == "-m" and args[2] in tools:
        args = [tools[args[2]], *args[3:]]
    return " ".join(shlex.quote(a) for a in args)


def _settings(args, campaign_file: Path) -> dict:
    return {"system": args.system, "time_scale": args.time_scale, "noise": args.noise,
            "effects": list(args.effect), "seed": args.seed, "starts": args.starts,
            "campaign": campaign_file.read_text()}


def _prepare(args, out: Path) -> tuple[Path, dict]:
    """The run folder with its campaign file and settings; a rerun must match them."""
    from .campaign import CampaignError, load_campaign
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {out}: exists and is not a folder")
    camp = out / "campaign.toml"
    if args.campaign:
        src = Path(args.campaign)
        try:
            cfg, text = load_campaign(src)
        except CampaignError as exc:
            raise ValueError(str(exc)) from None
        if cfg["campaign"]["rig"] != args.system:
            raise ValueError(f"{src}: the campaign is for the {cfg['campaign']['rig']} "
                             f"rig, but --system is {args.system}")
    else:
        text = resources.files("cbc_controller").joinpath(
            "demo_campaigns", f"{args.system}.toml").read_text()
    out.mkdir(parents=True, exist_ok=True)
    record = out / "demo.json"
    if record.exists() and (out / "campaign.h5").exists():
        before = json.loads(record.read_text())
        if camp.exists() and camp.read_text() != text:
            raise ValueError(f"{out} holds another campaign ({camp}); use another --out")
        # the physics must be the same for a resumed campaign; the pace may differ
        now = {"system": args.system, "noise": args.noise, "effects": list(args.effect),
               "seed": args.seed}
        diff = [k for k, v in now.items() if before.get("settings", {}).get(k) != v]
        if diff:
            raise ValueError(f"{out} was started with other settings ({', '.join(diff)}); "
                             "give the same ones to resume, or another --out")
    else:
        camp.write_text(text)
        before = {}
    return camp, before


def _campaign_state(h5: Path) -> str:
    """'none', 'completed' or 'partial'."""
    if not h5.exists():
        return "none"
    from .log import CampaignFileError, read_campaign
    try:
        c = read_campaign(str(h5))
    except CampaignFileError:
        return "partial"
    return "completed" if c.runs and c.runs[-1].get("stop_reason") == "completed" else "partial"


def run_demo(args) -> int:
    t0 = time.time()
    out = Path(args.out or f"runs/demo-{args.system}")
    try:
        camp_toml, previous = _prepare(args, out)
    except (ValueError, OSError) as exc:
        return _fail(str(exc))
    h5 = out / "campaign.h5"
    analysis = out / "analysis"
    record = {"version": __version__, "command": sys.argv, "settings": {
        k: v for k, v in _settings(args, camp_toml).items() if k != "campaign"},
        "started": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "runs": previous.get("runs", 0) + 1, "steps": {}, "seconds": {}}
    (out / "demo.json").write_text(json.dumps(record, indent=2) + "\n")
    py = sys.executable
    state = _campaign_state(h5)
    rig = child = None
    try:
        if state != "completed":
            _say(f"1/3 the rig: {args.system}, {args.time_scale:g} x real time, noise "
                 f"{args.noise:g}" + (f", hidden {' '.join(args.effect)}" if args.effect else ""))
            rig_args = [py, "-m", "rig_sim.cli", "serve", "--rig", args.system,
                        "--host", "127.0.0.1", "--port", "0", "--time-scale",
                        f"{args.time_scale:g}", "--noise", f"{args.noise:g}",
                        "--seed", str(args.seed)]
            if args.effect:
                rig_args += ["--effect", *args.effect]
            rig_log = open(out / "rig.log", "a")
            rig = _Child(rig_args, stdout=subprocess.PIPE, stderr=rig_log, text=True)
            line = rig.proc.stdout.readline()
            if not line:
                code = rig.proc.wait()
                tail = (out / "rig.log").read_text().strip().splitlines()
                # status 2 is the rig's "bad option" (an unknown --effect, say)
                return _fail(f"the rig did not start: {tail[-1] if tail else 'no output'}",
                             2 if code == 2 else 1)
            url = json.loads(line)["endpoints"][0]
            print(f"   {_shown(rig_args)}\n   serving at {url} (pid {rig.proc.pid}; its log: "
                  f"{out / 'rig.log'})", file=sys.stderr, flush=True)
            record["steps"]["rig"] = _shown(rig_args)

            if state == "partial":
                _say(f"2/3 the campaign, resumed from {h5}")
                camp_args = [py, "-m", "cbc_controller.cli", "run", "--resume", str(h5),
                             "--rig", url]
            else:
                _say(f"2/3 the campaign: CBC over Modbus TCP into {h5}")
                camp_args = [py, "-m", "cbc_controller.cli", "run", str(camp_toml),
                             "--rig", url, "--out", str(h5)]
            print(f"   {_shown(camp_args)}", file=sys.stderr, flush=True)
            record["steps"]["campaign"] = _shown(camp_args)
            t = time.time()
            child = _Child(camp_args, stdout=subprocess.DEVNULL)
            code = child.wait()
            record["seconds"]["campaign"] = round(time.time() - t, 1)
            child = None
            rig.stop()
            rig = None
            if code != 0:
                return _fail(f"the campaign ended with status {code}; what it logged is in "
                             f"{h5}; run the same command again to resume", 1)
        else:
            _say(f"1-2/3 the campaign in {h5} is complete: no rig needed")
        from .log import read_campaign
        from .report import plot_campaign
        plot_campaign(read_campaign(str(h5)), str(out / "campaign.png"))

        _say(f"3/3 the fit: mechanistic model, UDE, the missing physics -> {analysis}")
        fit_args = [py, "-m", "ude_fit.cli", "pipeline", str(h5), "--system", args.system,
                    "--starts", str(args.starts), "--seed", str(args.seed),
                    *SMOOTH_UDE.get(args.system, ()), "--out", str(analysis)]
        print(f"   {_shown(fit_args)}", file=sys.stderr, flush=True)
        record["steps"]["fit"] = _shown(fit_args)
        t = time.time()
        child = _Child(fit_args, stdout=subprocess.DEVNULL)
        code = child.wait()
        record["seconds"]["fit"] = round(time.time() - t, 1)
        child = None
        if not (analysis / "metrics.json").exists():
            return _fail(f"the fit ended with status {code}; see {analysis}", 1)
        fit_code = code       # 1: every UDE start diverged; the rest is still reported
    except KeyboardInterrupt:
        for c in (child, rig):
            if c is not None:
                c.interrupt() if c is child else c.stop()
        logged = ""
        if h5.exists():
            from .log import read_campaign
            logged = f"; {len(read_campaign(str(h5)).points)} points are logged in {h5}"
        print(f"\ncbc-demo: interrupted{logged}. The rig is stopped. Run the same command "
              "again to resume.", file=sys.stderr)
        return EXIT_INTERRUPTED
    finally:
        for c in (child, rig):
            if c is not None:
                c.stop()
        record["ended"] = datetime.now(timezone.utc).isoformat(timespec="seconds")
        record["seconds"]["total"] = round(time.time() - t0, 1)
        (out / "demo.json").write_text(json.dumps(record, indent=2) + "\n")

    summary = write_summary(out, h5, analysis, time.time() - t0)
    print_headline(out, summary)
    if fit_code != 0:
        print(f"cbc-demo: the fit ended with status {fit_code} (see "
              f"{analysis / 'fit' / 'report.md'})", file=sys.stderr)
        return 1
    return 0


def write_summary(out: Path, h5: Path, analysis: Path, seconds: float) -> dict:
    """DIR/metrics.json and DIR/report.md: the campaign and the analysis on one page."""
    from .log import read_campaign
    c = read_campaign(str(h5))
    a = json.loads((analysis / "metrics.json").read_text())
    stable = sum(1 for p in c.points if p.get("status", "ok") == "ok" and p.get("stable"))
    ok = [p for p in c.points if p.get("status", "ok") == "ok"]
    # rig time is the rig's own clock at each point; a resumed campaign restarts it
    rig_s = sum(max((p["rig_time"] for p in c.points if p.get("run") == r["run"]), default=0.0)
                for r in c.runs)
    campaign = {"file": "campaign.h5", "points": len(ok), "stable": stable,
                "unstable": len(ok) - stable, "failed": len(c.points) - len(ok),
                "runs": len(c.runs), "rig": c.rig,
                "device": (c.metadata.get("identity") or {}).get("model"),
                "started": c.started, "ended": c.ended}
    if ok and rig_s > 0:
        campaign["rig_seconds_per_point"] = rig_s / len(c.points)
    h = a["headline"]
    headline = {"points": campaign["points"], "stable": stable,
                "unstable": campaign["unstable"],
                "branch_error_before": h["branch_error_before"],
                "branch_error_after": h["branch_error_after"],
                "effects_added": h["effects_added"],
                "ude_branch_error": h["ude_branch_error"],
                "adequate_starts": h["adequate_starts"]}
    doc = {"version": __version__,
           "written": datetime.now(timezone.utc).isoformat(timespec="seconds"),
           "seconds": round(seconds, 1), "demo": json.loads((out / "demo.json").read_text()),
           "headline": headline, "campaign": campaign,
           "analysis": {k: a[k] for k in ("mechanistic", "ude", "refined", "starts", "effect",
                                          "added") if k in a},
           "files": {"campaign": "campaign.h5", "campaign_diagram": "campaign.png",
                     "diagram": "analysis/diagram.png", "report": "report.md",
                     "analysis_report": "analysis/report.md"}}
    tmp = out / "metrics.json.tmp"
    tmp.write_text(json.dumps(doc, indent=2, default=str) + "\n")
    os.replace(tmp, out / "metrics.json")
    (out / "report.md").write_text(_render(doc, a))
    return doc


def _pct(x) -> str:
    return "—" if x is None else f"{100 * x:.2f} %"


def _render(doc: dict, a: dict) -> str:
    h, c, d = doc["headline"], doc["campaign"], doc["demo"]
    s = d["settings"]
    what = {"flutter": "wind-tunnel aerofoil", "oscillator": "forced oscillator"}[s["system"]]
    eff = ", ".join(h["effects_added"]) or "nothing (no candidate improved the diagram)"
    lines = [f"# Demo run: the {what}", "",
             f"cbc-demo {doc['version']}, {doc['written']}, {doc['seconds']:.0f} s "
             f"(this invocation). Rig: {s['system']} at {s['time_scale']:g} x real time, noise "
             f"{s['noise']:g}, seed {s['seed']}"
             + (f", hidden physics planted: {' '.join(s['effects'])}" if s["effects"] else "")
             + ".", "",
             "## Headline", "",
             f"- **{h['points']} limit cycles** collected by CBC over Modbus: {h['stable']} "
             f"stable, {h['unstable']} unstable.",
             f"- Branch error of the mechanistic model **{_pct(h['branch_error_before'])}**; "
             f"after adding {eff}: **{_pct(h['branch_error_after'])}**.",
             f"- UDE (mechanistic + neural network): {_pct(h['ude_branch_error'])}, "
             f"{h['adequate_starts']} starts adequate.", "",
             "## The campaign", "",
             f"`campaign.h5`: {c['points']} points ({c['failed']} failed), {c['runs']} run(s), "
             f"device {c['device']}, from {c['started']} to {c['ended']}"
             + (f"; {c['rig_seconds_per_point']:.0f} rig-seconds per point"
                if "rig_seconds_per_point" in c else "") + ".", "",
             "![the collected limit cycles](campaign.png)", "",
             "The commands, as run:", "", "```sh"]
    lines += [d["steps"][k] for k in ("rig", "campaign", "fit") if k in d["steps"]]
    lines += ["```", "", "## The fitted models", "",
              "![measured points and model branches](analysis/diagram.png)", "",
              "| | mechanistic | UDE | refined |", "|---|---|---|---|"]
    m, u, r = a["mechanistic"], a.get("ude") or {}, a["refined"]
    for label, key in (("branch error, RMS (missed counted)", "branch_rms_with_missed"),
                       ("branch error, max", "branch_max")):
        lines.append(f"| {label} | {_pct(m.get(key))} | {_pct(u.get(key))} | "
                     f"{_pct(r.get(key))} |")
    lines.append(f"| missed points | {m.get('missed')} | {u.get('missed', '—')} | "
                 f"{r.get('missed')} |")
    lines += ["", "The whole analysis, with every start, the ranked candidate effects and "
              "their uncertainties: [analysis/report.md](analysis/report.md).", ""]
    return "\n".join(lines)


def print_headline(out: Path, doc: dict) -> None:
    h = doc["headline"]
    eff = ", ".join(h["effects_added"]) or "none"
    print(f"\ncbc-demo: done in {doc['seconds']:.0f} s. Run folder: {out}/\n"
          f"  report.md, metrics.json, campaign.h5, campaign.png, analysis/diagram.png\n"
          f"  {h['points']} limit cycles: {h['stable']} stable, {h['unstable']} unstable\n"
          f"  branch error: before {_pct(h['branch_error_before'])}, after "
          f"{_pct(h['branch_error_after'])} (added: {eff})\n"
          f"  UDE: {_pct(h['ude_branch_error'])}, {h['adequate_starts']} starts adequate")


def _interrupt(signum, frame):
    raise KeyboardInterrupt


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    # Ctrl-C, and a polite SIGTERM (docker stop, a batch system), stop the children in order
    signal.signal(signal.SIGINT, _interrupt)
    signal.signal(signal.SIGTERM, _interrupt)
    return run_demo(args)


def _entry() -> int:
    return main()


if __name__ == "__main__":
    sys.exit(_entry())
