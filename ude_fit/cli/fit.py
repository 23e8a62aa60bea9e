"""``ude-fit fit``: the mechanistic model and a UDE on one dataset, written to a folder."""

from __future__ import annotations

import sys

from ..fitting import fit
from ..report.files import provenance
from ..report.fit_files import write_fit
from ..report.format import pct
from .common import command_line, start
from .options import add_data_arguments, add_fit_arguments, fit_options


def add_parser(sub) -> None:
    p = sub.add_parser("fit", help="fit the mechanistic model and a UDE; write metrics, "
                       "report, diagrams and the fitted models")
    add_data_arguments(p)
    add_fit_arguments(p)
    p.add_argument("--out", required=True, metavar="DIR", help="output folder (created)")
    p.add_argument("--quiet", action="store_true", help="no progress on the terminal")


def run(args, argv) -> int:
    opts, ds, out, progress = start(args, fit_options)
    progress.say(f"{len(ds)} orbits loaded ({args.system}); fitting")
    res = fit(ds, opts, progress=progress)
    metrics = write_fit(out, ds, res, provenance(command_line(argv), args.data))
    kept = res.kept
    print(f"wrote {out}/: metrics.json, report.md, " + ", ".join(metrics["figures"].values())
          + ", mechanistic.eqx" + (", ude.eqx" if kept else ""))
    print(f"branch RMS error: mechanistic {pct(res.mechanistic_metrics.summary.branch_rms)}, "
          f"UDE {pct(kept.metrics.summary.branch_rms) if kept else 'no model'}; adequate "
          f"starts {res.adequate}/{opts.starts}")
    if res.mechanistic_controlled is not None:
        print(f"judged under the recorded control: mechanistic "
              f"{pct(res.mechanistic_judged.summary.branch_rms)} "
              f"({res.mechanistic_judged.summary.missed} missed), UDE "
              + (f"{pct(kept.judged.summary.branch_rms)} ({kept.judged.summary.missed} missed)"
                 if kept else "no model"))
    if res.ude is None:
        print(f"ude-fit: {res.why_no_ude()} (see report.md)", file=sys.stderr)
        return 1
    return 0
