"""``ude-fit explain``: the mechanistic model's residual (or a UDE's learnt correction)
explained as named physical effects, ranked."""

from __future__ import annotations

import os

from ..discovery.explain import explain
from ..discovery.routes import learnt_correction
from ..mechanistic_stage import identify_with_control
from ..model_file import load_model
from ..report.files import provenance, write_json, write_text
from ..report.loop_markdown import candidates_section, render_explain
from ..report.plots import parameter_label, plot_residuals
from ..training.identify import training_data
from .common import Progress, UsageError, command_line, out_dir
from .loop import add_common, data_and_control


def add_parser(sub) -> None:
    e = sub.add_parser("explain", help="explain the mechanistic model's residual (or a UDE's "
                       "learnt correction) as named physical effects, ranked")
    add_common(e)
    e.add_argument("--model", metavar="MODEL",
                   help="a UDE written by `ude-fit fit`: explain its learnt correction U too")


def run(args, argv) -> int:
    ds, choice = data_and_control(args)
    model = _model(args) if args.model else None     # checked before anything is written
    out = out_dir(args.out)
    progress = Progress(args.quiet)
    progress.say(f"{len(ds)} orbits loaded ({args.system}); explaining the residual")
    data = training_data(ds)
    control = None
    if choice is not None:      # the residual with the control's force as a known input
        data, _, ident = identify_with_control(ds, data, choice)
        control = ident["control"]
    ex = explain(data, args.system, seed=args.seed, bootstrap=args.bootstrap)
    doc = {**provenance(command_line(argv), args.data), "command_name": "explain",
           "data": ds.record(),
           "options": {k: v for k, v in vars(args).items()
                       if k not in ("data", "out", "quiet", "command")},
           "system": args.system,
           "what": "least-squares mechanistic model", "control": control,
           "explanation": ex.to_dict()}
    figures = {"residual against the states": "residuals.png"}
    plot_residuals(os.path.join(out, "residuals.png"), ex,
                   parameter_label=parameter_label(args.system))
    if model is not None:
        U = learnt_correction(model, data)
        exu = explain(data, args.system, seed=args.seed, bootstrap=args.bootstrap,
                      target=U)
        doc["correction"] = exu.to_dict()
        doc["correction"]["model"] = os.path.abspath(args.model)
    write_json(os.path.join(out, "explanation.json"), doc)
    text = render_explain(doc, figures)
    if args.model:
        text += "\n## The learnt correction U of `" + args.model + "`\n\n" + "\n".join(
            candidates_section(doc["correction"], args.system))
    write_text(os.path.join(out, "report.md"), text)
    print(f"wrote {out}/: explanation.json, report.md, residuals.png")
    print(ex.summary)
    for i, e in enumerate(ex.ranked[:5], 1):
        print(f"  {i}. {e['name']} ({e['key']}): " + ", ".join(
            f"{t} {c:.4g} ± {u:.2g}" for t, c, u in zip(e["terms"], e["coefficients"],
                                                        e["uncertainty"]))
            + f"; {100 * e['share']:.1f} % of the residual")
    return 0


def _model(args):
    model, header = load_model(args.model)
    if header["system"] != args.system:
        raise UsageError(f"--model {args.model}: a {header['system']} model, not "
                         f"{args.system}")
    if model.correction is None:
        raise UsageError(f"--model {args.model}: has no learnt correction to explain")
    return model
