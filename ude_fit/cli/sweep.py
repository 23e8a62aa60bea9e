"""``ude-fit sweep``: fit many datasets x fit options x seeds as Ray tasks (ude_fit.sweep)."""

from __future__ import annotations

from ..sweep import SweepError, load_sweep, run_sweep
from .common import UsageError


def add_parser(sub) -> None:
    s = sub.add_parser("sweep", help="fit many datasets x fit options x seeds as Ray tasks; "
                       "one summary table")
    s.add_argument("sweep", metavar="SWEEP.toml", help="the sweep file (see docs/cluster.md)")
    s.add_argument("--out", required=True, metavar="DIR",
                   help="output folder: summary.json, summary.md, fits/<id>/")
    s.add_argument("--address", metavar="ADDR", help="the Ray cluster to join (default: "
                   "$RAY_ADDRESS; with neither, a local Ray on this machine)")


def run(args, argv) -> int:
    try:
        return run_sweep(load_sweep(args.sweep), args.out, args.address)
    except SweepError as exc:
        raise UsageError(str(exc)) from None
