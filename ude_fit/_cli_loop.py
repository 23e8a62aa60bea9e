"""``ude-fit explain``, ``ude-fit refine`` and ``ude-fit loop`` (see ``_loop``).

    ude-fit explain DATA... --system S [--model UDE.eqx] --out DIR
    ude-fit refine DATA... --system S --add EFFECT[=SHAPE] ... [--ude] --out DIR
    ude-fit loop DATA... --system S [--max-effects N] [--min-gain G] [--ude] --out DIR
"""

from __future__ import annotations

import datetime as _dt
import os
import shlex


def add_parsers(sub) -> None:
    from ._cli_options import nonnegative_float as nonneg_float
    from ._cli_options import positive_int

    def common(p, *, seed_help="random seed of the cross-validation folds and bootstrap"):
        p.add_argument("data", nargs="+", metavar="DATA",
                       help="campaign HDF5 files, lee2020 .mat files, or folders of them")
        p.add_argument("--system", required=True, choices=("flutter", "oscillator"))
        p.add_argument("--seed", type=int, default=0, help=f"{seed_help} (default 0)")
        p.add_argument("--bootstrap", type=positive_int("--bootstrap"), default=200,
                       help="bootstrap resamples of the orbits for uncertainties (default 200)")
        p.add_argument("--out", required=True, metavar="DIR", help="output folder (created)")
        p.add_argument("--quiet", action="store_true", help="no progress on the terminal")

    def ude(p):
        p.add_argument("--ude", action="store_true",
                       help="also fit a NN UDE on the mechanistic and on the refined model")
        p.add_argument("--starts", type=positive_int("--starts"), default=3,
                       help="UDE starts with --ude (default 3)")

    e = sub.add_parser("explain", help="explain the mechanistic model's residual (or a UDE's "
                       "learnt correction) as named physical effects, ranked")
    common(e)
    e.add_argument("--model", metavar="MODEL",
                   help="a UDE written by `ude-fit fit`: explain its learnt correction U too")

    r = sub.add_parser("refine", help="add named effects to the mechanistic model, refit, "
                       "and compare before and after")
    common(r)
    r.add_argument("--add", nargs="+", required=True, metavar="EFFECT[=SHAPE]",
                   help="library effects to add (see `ude-fit explain`); SHAPE fixes a "
                   "freeplay gap or lag time constant, otherwise cross-validation picks it")
    ude(r)

    lp = sub.add_parser("loop", help="explain -> add the top-ranked effect -> refit, while "
                        "the diagram improves; report before and after")
    common(lp)
    lp.add_argument("--max-effects", type=positive_int("--max-effects"), default=3,
                    help="most effects to add (default 3)")
    lp.add_argument("--min-gain", type=nonneg_float("--min-gain"), default=0.1,
                    help="keep an effect only if the branch RMS error falls by this fraction "
                    "(or fewer points are missed; default 0.1)")
    ude(lp)


def _header(args, argv, name: str, ds) -> dict:
    from .cli import _inputs, _version
    return {"version": _version(),
            "written": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
            "command": "ude-fit " + " ".join(shlex.quote(a) for a in argv),
            "command_name": name, "inputs": _inputs(args.data),
            "data": {"points": len(ds), "sources": list(ds.sources)},
            "options": {k: v for k, v in vars(args).items()
                        if k not in ("data", "out", "quiet", "command")}}


def _param_label(system: str) -> str:
    return "airspeed (m/s)" if system == "flutter" else "forcing frequency (Hz)"


def cmd_explain(args, argv) -> int:
    import numpy as np

    from ._data import DataError, load
    from ._explain import explain
    from ._identify import augment, training_data
    from ._loop_report import render_explain
    from ._plots import plot_residuals
    from .cli import UsageError, _Progress, _out_dir, _write_json

    out = _out_dir(args.out)
    ds = load(args.data, args.system)
    if len(ds) == 0:
        raise DataError("the dataset is empty")
    progress = _Progress(args.quiet)
    progress._say(f"{len(ds)} orbits loaded ({args.system}); explaining the residual")
    data = training_data(ds)
    ex = explain(data, args.system, seed=args.seed, bootstrap=args.bootstrap)
    doc = {**_header(args, argv, "explain", ds), "system": args.system,
           "what": "least-squares mechanistic model", "explanation": ex.to_dict()}
    figures = {"residual against the states": "residuals.png"}
    plot_residuals(os.path.join(out, "residuals.png"), ex,
                   parameter_label=_param_label(args.system))
    if args.model:
        from ._io import load_model
        model, header = load_model(args.model)
        if header["system"] != args.system:
            raise UsageError(f"--model {args.model}: a {header['system']} model, not "
                             f"{args.system}")
        if model.correction is None:
            raise UsageError(f"--model {args.model}: has no learnt correction to explain")
        d2 = augment(data, model.mech)
        import jax
        feats = jax.vmap(jax.vmap(model.features, in_axes=(0, None)), in_axes=(0, 0))(
            d2.ys, d2.drive)
        U = np.asarray(jax.vmap(jax.vmap(model.correction))(feats))
        exu = explain(data, args.system, seed=args.seed, bootstrap=args.bootstrap,
                      target=U.reshape(-1, U.shape[-1]))
        doc["correction"] = exu.to_dict()
        doc["correction"]["model"] = os.path.abspath(args.model)
    _write_json(os.path.join(out, "explanation.json"), doc)
    text = render_explain(doc, figures)
    if args.model:
        from ._loop_report import candidates_section
        text += "\n## The learnt correction U of `" + args.model + "`\n\n" + "\n".join(
            candidates_section(doc["correction"], args.system))
    with open(os.path.join(out, "report.md"), "w") as fh:
        fh.write(text)
    print(f"wrote {out}/: explanation.json, report.md, residuals.png")
    print(ex.summary)
    for i, e in enumerate(ex.ranked[:5], 1):
        print(f"  {i}. {e['name']} ({e['key']}): " + ", ".join(
            f"{t} {c:.4g} ± {u:.2g}" for t, c, u in zip(e["terms"], e["coefficients"],
                                                        e["uncertainty"]))
            + f"; {100 * e['share']:.1f} % of the residual")
    return 0


def _finish(args, argv, name, ds, result) -> int:
    from ._fit import diagram_to_dict
    from ._io import save_model
    from ._loop import metrics_document
    from ._loop_report import render_loop
    from ._plots import plot_diagram, plot_residuals
    from .cli import _out_dir, _write_json

    out = _out_dir(args.out)
    doc = {**_header(args, argv, name, ds), **metrics_document(result)}
    figures = {}
    if result.explanations:
        plot_residuals(os.path.join(out, "residuals.png"), result.explanations[0],
                       parameter_label=_param_label(args.system))
        figures["residual of the mechanistic model against the states"] = "residuals.png"
    diagrams = {"mechanistic": result.before.diagram, "refined": result.after.diagram}
    for which in ("before", "after"):
        f = result.ude.get(which)
        if f is not None and f.ude is not None:
            diagrams[f"UDE on {'mechanistic' if which == 'before' else 'refined'}"] = \
                f.diagrams["ude"]
    plot_diagram(os.path.join(out, "diagram.png"), ds, diagrams,
                 title=f"{args.system}: before and after adding the effect")
    figures["bifurcation diagrams, before and after"] = "diagram.png"
    doc["figures"] = figures
    meta = dict(sources=list(ds.sources), ranges=result.ranges, version=doc["version"],
                written=doc["written"])
    save_model(os.path.join(out, "mechanistic.eqx"), result.before.model, role="mechanistic",
               scales=result.before.scales, diagram=diagram_to_dict(result.before.diagram),
               **meta)
    save_model(os.path.join(out, "refined.eqx"), result.after.model, role="refined",
               scales=result.after.scales, diagram=diagram_to_dict(result.after.diagram),
               **meta)
    models = {"mechanistic": "mechanistic.eqx", "refined": "refined.eqx"}
    for which, fname in (("before", "ude_mechanistic.eqx"), ("after", "ude_refined.eqx")):
        f = result.ude.get(which)
        if f is not None and f.ude is not None and (which == "before" or result.added):
            save_model(os.path.join(out, fname), f.ude, role=f"ude ({which})",
                       scales=f.scales, diagram=diagram_to_dict(f.diagrams["ude"]), **meta)
            models[f"ude_{which}"] = fname
    doc["models"] = models
    _write_json(os.path.join(out, "metrics.json"), doc)
    with open(os.path.join(out, "report.md"), "w") as fh:
        fh.write(render_loop(doc, figures))
    b, a = doc["before"], doc["after"]
    eff = doc["effect"]
    print(f"wrote {out}/: metrics.json, report.md, " + ", ".join(figures.values()) + ", "
          + ", ".join(models.values()))
    print(f"effect: {eff['name'] + ' (' + eff['key'] + ')' if eff else 'none added'}; "
          f"branch RMS error (missed points counted): before "
          f"{100 * b['branch_rms_with_missed']:.2f} %, after "
          f"{100 * a['branch_rms_with_missed']:.2f} %")
    return 0


def _ude_options(args):
    from ._fit import FitOptions
    return FitOptions(system=args.system, starts=args.starts, seed=args.seed)


def cmd_refine(args, argv) -> int:
    from ._data import load
    from ._loop import fit_udes, parse_add, refine
    from .cli import UsageError, _Progress
    try:
        add = parse_add(args.system, args.add)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    ds = load(args.data, args.system)
    progress = _Progress(args.quiet)
    res = refine(ds, args.system, add, seed=args.seed, bootstrap=args.bootstrap,
                 progress=progress)
    if args.ude:
        fit_udes(res, ds, _ude_options(args), progress=progress)
    return _finish(args, argv, "refine", ds, res)


def cmd_loop(args, argv) -> int:
    from ._data import load
    from ._loop import close_loop, fit_udes
    from .cli import UsageError, _Progress
    if args.min_gain >= 1:
        raise UsageError(f"--min-gain must be below 1, not {args.min_gain}")
    ds = load(args.data, args.system)
    progress = _Progress(args.quiet)
    res = close_loop(ds, args.system, max_effects=args.max_effects, min_gain=args.min_gain,
                     seed=args.seed, bootstrap=args.bootstrap, progress=progress)
    if args.ude:
        fit_udes(res, ds, _ude_options(args), progress=progress)
    return _finish(args, argv, "loop", ds, res)
