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


def summary(res, starts: int) -> list[str]:
    """The lines the command prints about the fit ``res`` of ``starts`` starts: the branch
    errors and the adequate starts, and, with the control as an input, the figures the
    adequacy read (each model's orbits under the recorded control) and the warning of a
    branch whose invasive points all lie on one side of the kept UDE's orbits."""
    kept = res.kept
    lines = [f"branch RMS error: mechanistic {pct(res.mechanistic_metrics.summary.branch_rms)}, "
             f"UDE {pct(kept.metrics.summary.branch_rms) if kept else 'no model'}; adequate "
             f"starts {res.adequate}/{starts}"]
    if res.mechanistic_controlled is not None:
        judged = lambda m: f"{pct(m.summary.branch_rms)} ({m.summary.missed} missed)"
        lines.append(f"judged under the recorded control: mechanistic "
                     f"{judged(res.mechanistic_judged)}, UDE "
                     + (judged(kept.judged) if kept else "no model"))
    if kept and kept.controlled is not None and kept.controlled.invasive:
        warning = kept.controlled.held_sides(kept.metrics).warning()
        if warning:
            lines.append(warning)
    return lines


def run(args, argv) -> int:
    opts, ds, out, progress = start(args, fit_options)
    progress.say(f"{len(ds)} orbits loaded ({args.system}); fitting")
    res = fit(ds, opts, progress=progress)
    metrics = write_fit(out, ds, res, provenance(command_line(argv), args.data))
    print(f"wrote {out}/: metrics.json, report.md, " + ", ".join(metrics["figures"].values())
          + ", mechanistic.eqx" + (", ude.eqx" if res.kept else ""))
    print("\n".join(summary(res, opts.starts)))
    if res.ude is None:
        print(f"ude-fit: {res.why_no_ude()} (see report.md)", file=sys.stderr)
        return 1
    return 0
