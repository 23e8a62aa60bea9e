"""Adequate starts on the real wind-tunnel data (lee2020/model2) by seed: prints one JSON object.

For each seed, `ude-fit fit DATA --system flutter --seed S` as a user types it (the fit's
own defaults, then the given extra options), then per start: branch RMS, missed points,
folds, Hopf point, adequate; and per seed the count of adequate starts, the number of
starts, the wall time and the training's share of it. The adequacy count moves with the seed
more than with most settings, so a setting is judged over several seeds, not one.

    python3 benchmarks/lee2020_benchmark.py [--data DIR] [--seeds 0,1,2] [-- extra fit options]

e.g. the regularised fit the test uses:

    python3 benchmarks/lee2020_benchmark.py -- --width 48 --starts 5 --energy-shape 3 \\
        --rest-stability 30 --energy-rising 10000
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import sys
import tempfile
import time

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

from ude_fit import cli  # noqa: E402
from ude_fit.cli.compile_cache import ENV as COMPILE_CACHE  # noqa: E402

# wall times include compilation, as the figures in docs/benchmarks.md always have: the
# command line's on-disk cache of compiled code is off here (unless JAX is given one)
os.environ[COMPILE_CACHE] = ""

DEFAULT_DATA = os.path.join(os.path.dirname(__file__), "..", "..", "shared", "data", "lee2020",
                            "model2")


def _guide_rounds(record: dict) -> dict:
    """A start's folds and missed points before its guide rounds and the rounds run, where
    it had any."""
    g = record.get("guide_rounds")
    return {} if g is None else {"folds_before_guide_rounds": g["folds_before"],
                                 "missed_before_guide_rounds": g["missed_before"],
                                 "guide_rounds_run": len(g["rounds"]),
                                 "guide_round_kept": g["kept_round"]}


def one_seed(data: str, seed: int, extra: list[str]) -> dict:
    with tempfile.TemporaryDirectory() as out:
        t0 = time.perf_counter()
        with contextlib.redirect_stdout(sys.stderr):    # stdout carries the JSON alone
            rc = cli.main(["fit", data, "--system", "flutter", "--seed", str(seed), *extra,
                           "--out", out, "--quiet"])
        wall = time.perf_counter() - t0
        if not os.path.exists(os.path.join(out, "metrics.json")):
            raise SystemExit(f"lee2020_benchmark: ude-fit fit exited {rc} without metrics "
                             f"(options: {' '.join(extra)})")
        with open(os.path.join(out, "metrics.json")) as fh:
            m = json.load(fh)
    starts = [{"start": r["start"], "adequate": r["adequate"],
               **({k: r["metrics"][k] for k in ("branch_rms", "missed", "fold_count")}
                  | {"hopf": (r["metrics"]["hopf"] or {}).get("model")}
                  | _guide_rounds(r) | _where(r) | _judged(r)
                  if r.get("metrics") else {"status": r["status"]})}
              for r in m["starts"]["records"]]
    return {"seed": seed, "exit": rc, "adequate": m["starts"]["adequate"],
            "starts_run": len(m["starts"]["records"]),
            "trained_together": m["starts"].get("trained_together"),
            "train_s": round(m["starts"].get("train_seconds") or float("nan"), 1),
            "kept": m["starts"]["kept"], "kept_by": m["starts"].get("kept_by"),
            "data_scatter": m["data"]["scatter"],
            "ude_branch_rms": (m["ude"] or {}).get("branch_rms"),
            "mechanistic_branch_rms": m["mechanistic"]["branch_rms"],
            "judged_by": m["starts"]["criterion"].get("judged_by"),
            **{f"mechanistic_{k}": v for k, v in _judged(m["mechanistic"]).items()},
            "wall_s": round(wall, 1), "starts": starts}


def _judged(r: dict) -> dict:
    """What the adequacy read of a model fitted with the control as an input: its branch
    RMS and missed points under the recorded control, where its diagram has each point's
    stability (nothing without the option)."""
    judged = (r.get("controlled") or {}).get("judged")
    return {} if judged is None else {"judged_branch_rms": judged["branch_rms"],
                                      "judged_missed": judged["missed"]}


def _where(r: dict) -> dict:
    """Where a start's folds lie (m/s, mm) and whether its Hopf point is subcritical."""
    crit = r.get("hopf_criticality") or {}
    return {"folds_at": [[round(f["param"], 2), round(1e3 * f["amplitude"], 1)]
                         for f in r["metrics"].get("fold_points") or []],
            "hopf_subcritical": crit.get("subcritical")}


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    extra = argv[argv.index("--") + 1:] if "--" in argv else []
    own = argv[:argv.index("--")] if "--" in argv else argv
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", default=DEFAULT_DATA, help="the lee2020/model2 folder")
    p.add_argument("--seeds", default="0,1,2", help="comma-separated seeds (default 0,1,2)")
    args = p.parse_args(own)
    if not os.path.isdir(args.data):
        p.error(f"--data: no such folder: {args.data}")
    try:
        seeds = [int(s) for s in args.seeds.split(",")]
    except ValueError:
        p.error(f"--seeds: not a comma-separated list of integers: {args.seeds!r}")
    runs = [one_seed(args.data, s, extra) for s in seeds]
    counts = sorted(r["adequate"] for r in runs)
    print(json.dumps({"benchmark": "lee2020_adequacy", "options": extra, "seeds": seeds,
                      "adequate_per_seed": [r["adequate"] for r in runs],
                      "adequate_median": counts[len(counts) // 2],
                      "seeds_with_80_percent_adequate": sum(
                          r["adequate"] >= 0.8 * r["starts_run"] for r in runs),
                      "wall_s_median": sorted(r["wall_s"] for r in runs)[len(runs) // 2],
                      "runs": runs}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
