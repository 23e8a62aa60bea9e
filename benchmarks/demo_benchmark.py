"""Wall time of the lab's demo (the README's main job), per stage. Prints one JSON object.

    python3 benchmarks/demo_benchmark.py                     # flutter demo, this install
    python3 benchmarks/demo_benchmark.py --system oscillator
    python3 benchmarks/demo_benchmark.py --readme            # the README's exact command, in a
                                                             # fresh clone and a fresh venv

`--readme` clones this repository (its committed HEAD) into a temporary folder, makes a new
virtual environment, puts it first on PATH and runs the README's main-job command there:
install plus demo, as a new user would. pip's download cache is not cleared, so the install
time is that of a machine that has fetched the wheels before.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def readme_command() -> str:
    text = (REPO / "README.md").read_text()
    m = re.search(r"<!-- main-job-command -->\s*```sh\n(.+?)\n```", text, re.S)
    if not m:
        sys.exit("demo_benchmark: no main-job command in README.md")
    return m.group(1).strip()


def figures(run: Path) -> dict:
    demo = json.loads((run / "demo.json").read_text())
    m = json.loads((run / "metrics.json").read_text())
    h = m["headline"]
    out = {"stage_seconds": demo.get("seconds", {}), "points": h["points"],
           "stable": h["stable"], "unstable": h["unstable"],
           "branch_error_before": h["branch_error_before"],
           "branch_error_after": h["branch_error_after"], "effects_added": h["effects_added"],
           "ude_branch_error": h["ude_branch_error"], "adequate_starts": h["adequate_starts"]}
    if "rig_seconds_per_point" in m["campaign"]:
        out["rig_seconds_per_point"] = round(m["campaign"]["rig_seconds_per_point"], 1)
    return out


def run_here(system: str, starts: int) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        run = Path(tmp) / "run"
        t = time.perf_counter()
        r = subprocess.run([sys.executable, "-m", "cbc_controller.demo", "--system", system,
                            "--starts", str(starts), "--out", str(run)],
                           capture_output=True, text=True)
        wall = time.perf_counter() - t
        if r.returncode != 0:
            sys.exit(f"demo_benchmark: the demo failed: {r.stderr.strip().splitlines()[-1]}")
        return {"wall_s": round(wall, 1), **figures(run)}


def run_readme() -> dict:
    cmd = readme_command()
    with tempfile.TemporaryDirectory() as tmp:
        clone = Path(tmp) / "clone"
        subprocess.run(["git", "clone", "-q", str(REPO), str(clone)], check=True)
        venv = Path(tmp) / "venv"
        subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
        env = {**os.environ, "PATH": f"{venv / 'bin'}:{os.environ['PATH']}",
               "VIRTUAL_ENV": str(venv)}
        env.pop("PYTHONPATH", None)
        t = time.perf_counter()
        r = subprocess.run(["bash", "-c", cmd], cwd=clone, env=env, capture_output=True,
                           text=True)
        wall = time.perf_counter() - t
        if r.returncode != 0:
            sys.exit(f"demo_benchmark: the README command failed: "
                     f"{r.stderr.strip().splitlines()[-1]}")
        run = clone / "runs" / "demo-flutter"
        fig = figures(run)
        demo_s = fig["stage_seconds"].get("total", 0.0)
        return {"command": cmd, "wall_s": round(wall, 1),
                "install_s": round(wall - demo_s, 1), **fig}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--system", choices=("flutter", "oscillator"), default="flutter")
    p.add_argument("--starts", type=int, default=3)
    p.add_argument("--readme", action="store_true",
                   help="the README's command in a fresh clone and venv (flutter)")
    args = p.parse_args()
    out = {"benchmark": "demo", "machine": {"cpus": os.cpu_count(),
                                             "python": platform.python_version()}}
    if args.readme:
        out["readme"] = run_readme()
    else:
        out[args.system] = run_here(args.system, args.starts)
    print(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
