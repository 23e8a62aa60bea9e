"""``ude-fit pipeline``: the whole offline job (:func:`ude_fit.run_pipeline`) on one
dataset, with one summary: ``DIR/fit`` (as ``ude-fit fit``), ``DIR/loop`` (as ``ude-fit
loop``), ``DIR/report.md``, ``DIR/metrics.json`` and ``DIR/diagram.png``. It takes every
option ``ude-fit fit`` takes (the same argument group). This is what the demo and the
compose file's ``fit`` service run."""

from __future__ import annotations

import argparse
import sys

from ..pipeline import PipelineOptions, run_pipeline
from ..report.files import provenance
from ..report.pipeline_files import write_pipeline
from ..report.pipeline_markdown import headline_text
from .common import command_line, start
from .options import add_data_arguments, add_fit_arguments, fit_options, positive_int


def add_parser(sub) -> None:
    p = sub.add_parser("pipeline", help="fit, then close the loop, then one summary report "
                       "(what the demo runs)")
    add_data_arguments(p)
    add_fit_arguments(p)
    p.add_argument("--max-effects", type=positive_int("--max-effects"), default=3,
                   help="most effects the loop adds (default 3)")
    p.add_argument("--locate-shapes", action=argparse.BooleanOptionalAction, default=True,
                   help="the loop also locates the residual as shapes and tries their forms "
                   "beside the catalogue's (default: on; --no-locate-shapes: the catalogue only)")
    p.add_argument("--out", required=True, metavar="DIR",
                   help="output folder (created); fit/ and loop/ go inside")
    p.add_argument("--quiet", action="store_true", help="no progress on the terminal")


def pipeline_options(args) -> PipelineOptions:
    """The options the flags ask for; ValueError (naming the option) if they make none."""
    return PipelineOptions(fit=fit_options(args), max_effects=args.max_effects,
                           locate_shapes=args.locate_shapes)


def run(args, argv) -> int:
    opts, ds, out, progress = start(args, pipeline_options, lambda o: o.fit)
    result = run_pipeline(ds, opts, progress=progress)
    doc = write_pipeline(out, ds, result, provenance(command_line(argv), args.data))
    print(f"wrote {out}/: report.md, metrics.json, diagram.png, fit/, loop/")
    print(headline_text(doc["headline"]))
    if result.fit.ude is None:
        print(f"ude-fit: {result.fit.why_no_ude()} (see fit/report.md)", file=sys.stderr)
        return 1
    return 0
