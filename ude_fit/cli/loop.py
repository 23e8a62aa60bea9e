"""``ude-fit refine`` (add named effects, refit, compare) and ``ude-fit loop`` (explain ->
add the top-ranked effect -> refit, while the diagram improves)."""

from __future__ import annotations

import argparse

from ..discovery.loop import close_loop, fit_udes, refine
from ..models.library import parse_effects
from ..report.files import provenance
from ..report.loop_files import write_loop
from ..training.options import FitOptions
from .common import Progress, UsageError, command_line, load_data, out_dir
from .options import (add_control_arguments, add_data_arguments, add_sensor_zero_argument,
                      control_choice, nonnegative_float, positive_int)


def add_common(p) -> None:
    """What explain, refine and loop share."""
    add_data_arguments(p)
    add_control_arguments(p)
    add_sensor_zero_argument(p)
    p.add_argument("--seed", type=int, default=0, help="random seed of the cross-validation "
                   "folds and bootstrap (default 0)")
    p.add_argument("--bootstrap", type=positive_int("--bootstrap"), default=200,
                   help="bootstrap resamples of the orbits for uncertainties (default 200)")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder (created)")
    p.add_argument("--quiet", action="store_true", help="no progress on the terminal")


def _add_ude(p) -> None:
    p.add_argument("--ude", action="store_true",
                   help="also fit a NN UDE on the mechanistic and on the refined model, "
                   "and locate the first one's learnt correction as the residual is located "
                   "(the two routes; metrics.json's routes says whether they agree)")
    p.add_argument("--starts", type=positive_int("--starts"), default=3,
                   help="UDE starts with --ude (default 3)")


def add_parsers(sub) -> None:
    r = sub.add_parser("refine", help="add named effects to the mechanistic model, refit, "
                       "and compare before and after")
    add_common(r)
    r.add_argument("--add", nargs="+", required=True, metavar="EFFECT[=SHAPE]",
                   help="library effects to add (see `ude-fit explain`); SHAPE fixes a "
                   "freeplay gap or lag time constant, otherwise cross-validation picks it")
    _add_ude(r)

    lp = sub.add_parser("loop", help="explain -> add the top-ranked effect -> refit, while "
                        "the diagram improves; report before and after")
    add_common(lp)
    lp.add_argument("--max-effects", type=positive_int("--max-effects"), default=3,
                    help="most effects to add (default 3)")
    lp.add_argument("--min-gain", type=nonnegative_float("--min-gain"), default=0.1,
                    help="keep an effect only if the branch RMS error falls by this fraction "
                    "(or fewer points are missed; default 0.1)")
    lp.add_argument("--locate-shapes", action=argparse.BooleanOptionalAction, default=True,
                    help="also locate the residual as shapes of single states (and a "
                    "velocity's coefficient as a shape of a displacement), name their class "
                    "and try the form beside the catalogue's candidate (default: on; "
                    "--no-locate-shapes tries the catalogue only)")
    _add_ude(lp)


def data_and_control(args):
    """The dataset about the sensors' zero --sensor-zero asks for (chosen as a fit chooses
    it, :func:`~ude_fit.mechanistic_stage.with_chosen_zero`), and the control choice,
    checked before anything is written: a bad --control-gain, or --control-input on data
    without control records, is a usage error."""
    from ..mechanistic_stage import with_chosen_zero
    from ..training.control import control_input
    try:
        choice = control_choice(args)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    ds = load_data(args)
    if choice is not None:
        control_input(ds, choice.gain)      # a DataError naming a point without a record
    zero = FitOptions(system=args.system, sensor_zero=args.sensor_zero,
                      control_input=choice is not None,
                      control_gain=None if choice is None else choice.gain)
    return with_chosen_zero(ds, zero), choice


def _options(args) -> dict:
    return {k: v for k, v in vars(args).items() if k not in ("data", "out", "quiet", "command")}


def _finish(args, argv, name, ds, result, progress) -> int:
    out = out_dir(args.out)
    if args.ude:
        fit_udes(result, ds, FitOptions(system=args.system, starts=args.starts,
                                        seed=args.seed), progress=progress,
                 seed=args.seed, bootstrap=args.bootstrap)
    doc = write_loop(out, ds, result, provenance(command_line(argv), args.data), name=name,
                     options=_options(args))
    b, a = result.before.metrics.summary, result.after.metrics.summary
    eff = doc["effect"]
    print(f"wrote {out}/: metrics.json, report.md, " + ", ".join(doc["figures"].values())
          + ", " + ", ".join(doc["models"].values()))
    print(f"effect: {eff['name'] + ' (' + eff['key'] + ')' if eff else 'none added'}; "
          f"branch RMS error (missed points counted): before "
          f"{100 * b.branch_rms_with_missed:.2f} %, after "
          f"{100 * a.branch_rms_with_missed:.2f} %")
    return 0


def run_refine(args, argv) -> int:
    try:
        add = list(parse_effects(args.system, args.add))
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    ds, choice = data_and_control(args)
    progress = Progress(args.quiet)
    res = refine(ds, args.system, add, seed=args.seed, bootstrap=args.bootstrap,
                 progress=progress, control=choice)
    return _finish(args, argv, "refine", ds, res, progress)


def run_loop(args, argv) -> int:
    if args.min_gain >= 1:
        raise UsageError(f"--min-gain must be below 1, not {args.min_gain}")
    ds, choice = data_and_control(args)
    progress = Progress(args.quiet)
    res = close_loop(ds, args.system, max_effects=args.max_effects, min_gain=args.min_gain,
                     seed=args.seed, bootstrap=args.bootstrap,
                     locate_shapes=args.locate_shapes, progress=progress, control=choice)
    return _finish(args, argv, "loop", ds, res, progress)
