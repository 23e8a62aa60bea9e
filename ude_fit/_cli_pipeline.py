"""``ude-fit pipeline``: the whole offline job on one dataset, with one summary.

    ude-fit pipeline DATA... --system S [--starts N] [--seed S] --out DIR

Runs ``ude-fit fit`` into ``DIR/fit`` (mechanistic model and UDE) and ``ude-fit loop`` into
``DIR/loop`` (the missing physics named, added and refitted), then writes ``DIR/report.md``,
``DIR/metrics.json`` and ``DIR/diagram.png`` (every model over the data) with the headline
figures. This is what the demo and the compose file's ``fit`` service run.
"""

from __future__ import annotations

import argparse
import json
import os

_KEYS = ("branch_rms", "branch_rms_with_missed", "branch_max", "missed", "trajectory_rms",
         "hopf", "fold")


def add_parser(sub) -> None:
    from ._cli_options import finite_float, positive_int, positive_float
    from ._cli_options import nonnegative_float as nonneg_float
    p = sub.add_parser("pipeline", help="fit, then close the loop, then one summary report "
                       "(what the demo runs)")
    p.add_argument("data", nargs="+", metavar="DATA",
                   help="campaign HDF5 files, lee2020 .mat files, or folders of them")
    p.add_argument("--system", required=True, choices=("flutter", "oscillator"))
    p.add_argument("--starts", type=positive_int("--starts"), default=5,
                   help="UDE random starts (default 5)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--equilibrium-penalty", type=nonneg_float("--equilibrium-penalty"),
                   metavar="W", help="aerofoil UDE: as `ude-fit fit --equilibrium-penalty`")
    p.add_argument("--smoothness-penalty", type=nonneg_float("--smoothness-penalty"),
                   metavar="W", help="aerofoil UDE: as `ude-fit fit --smoothness-penalty`")
    p.add_argument("--param-scale", type=positive_float("--param-scale"), default=1.0,
                   metavar="F", help="UDE: as `ude-fit fit --param-scale` (default 1)")
    p.add_argument("--max-effects", type=positive_int("--max-effects"), default=3,
                   help="most effects the loop adds (default 3)")
    p.add_argument("--reference-hopf", type=finite_float("--reference-hopf"), metavar="V",
                   help="known Hopf airspeed (m/s) for the error figures")
    p.add_argument("--reference-fold", type=finite_float("--reference-fold"), metavar="V",
                   help="known fold airspeed (m/s) for the error figures")
    p.add_argument("--out", required=True, metavar="DIR",
                   help="output folder (created); fit/ and loop/ go inside")
    p.add_argument("--quiet", action="store_true", help="no progress on the terminal")


def _pick(m: dict | None) -> dict | None:
    return None if m is None else {k: m.get(k) for k in _KEYS}


def cmd_pipeline(args, argv) -> int:
    from ._data import load
    from ._fit import diagram_from_dict
    from ._io import load_model
    from ._plots import plot_diagram
    from .cli import (UsageError, _inputs, _out_dir, _Progress, _version, _write_json,
                      cmd_fit)
    from ._cli_loop import cmd_loop
    import datetime as _dt
    import shlex

    if (args.reference_hopf is not None or args.reference_fold is not None) \
            and args.system != "flutter":
        raise UsageError("--reference-hopf/--reference-fold apply to --system flutter only")
    out = _out_dir(args.out)
    ds = load(args.data, args.system)       # bad input fails here, before any work
    progress = _Progress(args.quiet)
    stable = sum(1 for o in ds if o.stable is True)
    unstable = sum(1 for o in ds if o.stable is False)

    progress._say(f"pipeline 1/2: fit (mechanistic model and UDE, {args.starts} starts) "
                  f"-> {os.path.join(out, 'fit')}")
    fit_args = argparse.Namespace(
        data=args.data, system=args.system, approximator="nn", training="periodic",
        mechanistic="equation", starts=args.starts, seed=args.seed, width=12, depth=2,
        weight_decay=0.0, equilibrium_penalty=args.equilibrium_penalty or 0.0,
        smoothness_penalty=args.smoothness_penalty or 0.0, param_scale=args.param_scale,
        param_dependence="input", param_degree=2, rest_stability=0.0, energy_shape=0.0,
        energy_rising=0.0,
        reference_hopf=args.reference_hopf, reference_fold=args.reference_fold,
        out=os.path.join(out, "fit"), quiet=args.quiet)
    extra = [f"--{k.replace('_', '-')}={getattr(args, k)}"
             for k in ("equilibrium_penalty", "smoothness_penalty")
             if getattr(args, k) is not None]
    if args.param_scale != 1.0:
        extra.append(f"--param-scale={args.param_scale}")
    fit_status = cmd_fit(fit_args, ["fit", *args.data, "--system", args.system,
                                    "--starts", str(args.starts), "--seed", str(args.seed),
                                    *extra, "--out", fit_args.out])
    progress._say(f"pipeline 2/2: close the loop (explain, add, refit) -> "
                  f"{os.path.join(out, 'loop')}")
    loop_args = argparse.Namespace(
        data=args.data, system=args.system, seed=args.seed, bootstrap=200,
        out=os.path.join(out, "loop"), quiet=args.quiet, max_effects=args.max_effects,
        min_gain=0.1, ude=False, starts=3)
    cmd_loop(loop_args, ["loop", *args.data, "--system", args.system, "--seed",
                         str(args.seed), "--max-effects", str(args.max_effects),
                         "--out", loop_args.out])

    with open(os.path.join(out, "fit", "metrics.json")) as fh:
        fitm = json.load(fh)
    with open(os.path.join(out, "loop", "metrics.json")) as fh:
        loopm = json.load(fh)

    diagrams = {}
    for label, path in (("mechanistic", ("fit", "mechanistic.eqx")),
                        ("UDE", ("fit", "ude.eqx")),
                        ("refined", ("loop", "refined.eqx"))):
        f = os.path.join(out, *path)
        if os.path.exists(f) and (label != "refined" or loopm["added"]):
            diagrams[label] = diagram_from_dict(load_model(f)[1]["diagram"])
    plot_diagram(os.path.join(out, "diagram.png"), ds, diagrams,
                 title=f"{args.system}: measured points, fitted and refined models")

    before, after = loopm["before"], loopm["after"]
    effects = [s.get("name") for s in loopm["steps"] if s.get("kept")]
    headline = {
        "points": len(ds), "stable": stable, "unstable": unstable,
        "branch_error_before": before["branch_rms_with_missed"],
        "branch_error_after": after["branch_rms_with_missed"],
        "missed_before": before["missed"], "missed_after": after["missed"],
        "ude_branch_error": (fitm["ude"] or {}).get("branch_rms_with_missed"),
        "adequate_starts": f"{fitm['starts']['adequate']}/{args.starts}",
        "effects_added": effects,
    }
    doc = {
        "version": _version(),
        "written": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "command": "ude-fit " + " ".join(shlex.quote(a) for a in argv),
        "inputs": _inputs(args.data),
        "options": {k: v for k, v in vars(args).items()
                    if k not in ("data", "out", "quiet", "command")},
        "system": args.system,
        "data": {"points": len(ds), "stable": stable, "unstable": unstable,
                 "sources": list(ds.sources),
                 "parameter_range": [min(o.parameter for o in ds), max(o.parameter for o in ds)]},
        "headline": headline,
        "mechanistic": _pick(fitm["mechanistic"]),
        "ude": _pick(fitm["ude"]),
        "starts": {k: fitm["starts"][k] for k in ("adequate", "requested")
                   if k in fitm["starts"]},
        "refined": _pick(after),
        "effect": loopm["effect"], "added": loopm["added"],
        "reports": {"fit": "fit/report.md", "loop": "loop/report.md"},
        "figures": {"all models over the data": "diagram.png",
                    "fit": {k: f"fit/{v}" for k, v in fitm["figures"].items()},
                    "loop": {k: f"loop/{v}" for k, v in loopm["figures"].items()}},
    }
    _write_json(os.path.join(out, "metrics.json"), doc)
    with open(os.path.join(out, "report.md"), "w") as fh:
        fh.write(render_pipeline(doc, fitm, loopm))
    print(f"wrote {out}/: report.md, metrics.json, diagram.png, fit/, loop/")
    print(headline_text(headline))
    return fit_status


def headline_text(h: dict) -> str:
    pct = lambda x: "—" if x is None else f"{100 * x:.2f} %"       # noqa: E731
    eff = ", ".join(h["effects_added"]) or "none"
    return (f"{h['points']} points ({h['stable']} stable, {h['unstable']} unstable); "
            f"branch error before {pct(h['branch_error_before'])}, after "
            f"{pct(h['branch_error_after'])} (added: {eff}); UDE {pct(h['ude_branch_error'])}, "
            f"{h['adequate_starts']} starts adequate")


def _num(x, fmt="{:.3f}"):
    return "—" if x is None else fmt.format(x)


def _loc(d):
    if not d or d.get("model") is None:
        return "—"
    err = d.get("error")
    return f"{d['model']:.3f}" + ("" if err is None else f" ({err:+.3f})")


def render_pipeline(doc: dict, fitm: dict, loopm: dict) -> str:
    h = doc["headline"]
    sysname = {"flutter": "aerofoil (flutter)", "oscillator": "forced oscillator"}[doc["system"]]
    pct = lambda x: "—" if x is None else f"{100 * x:.2f} %"        # noqa: E731
    lines = [f"# The lab's report: {sysname}", "",
             f"Written by ude_fit {doc['version']} on {doc['written']}; command "
             f"`{doc['command']}`.", "",
             "## Headline", "",
             f"- {h['points']} limit cycles measured: {h['stable']} stable, "
             f"{h['unstable']} unstable.",
             f"- Branch amplitude error of the mechanistic model "
             f"{pct(h['branch_error_before'])} ({h['missed_before']} points missed); after "
             f"adding {', '.join(h['effects_added']) or 'nothing (no effect improved it)'}: "
             f"{pct(h['branch_error_after'])} ({h['missed_after']} missed). Missed points "
             "count at their measured amplitude.",
             f"- UDE (mechanistic model + neural network): {pct(h['ude_branch_error'])}; "
             f"{h['adequate_starts']} random starts adequate.", "",
             "![every model over the data](diagram.png)", "",
             "## Data", ""]
    d = doc["data"]
    what = ("airspeed", "m/s") if doc["system"] == "flutter" else \
        ("forcing amplitude", "m/s²")
    lines += [f"{d['points']} periodic orbits, {what[0]} {d['parameter_range'][0]:.4g} to "
              f"{d['parameter_range'][1]:.4g} {what[1]}, from "
              + ", ".join(f"`{s}`" for s in d["sources"]) + ".", "",
              "## The models side by side", "",
              "| | mechanistic | UDE | refined (loop) |", "|---|---|---|---|"]
    m, u, r = doc["mechanistic"], doc["ude"] or {}, doc["refined"]
    rows = [("branch error, RMS (missed counted)", "branch_rms_with_missed", pct),
            ("branch error, max", "branch_max", pct),
            ("missed points", "missed", lambda x: _num(x, "{}")),
            ("one-period trajectory error, RMS", "trajectory_rms", pct),
            ("Hopf (error)", "hopf", _loc), ("fold (error)", "fold", _loc)]
    if doc["system"] != "flutter":
        rows = rows[:4]               # the forced oscillator has folds per frequency only
    for label, key, f in rows:
        lines.append(f"| {label} | {f(m.get(key))} | {f(u.get(key))} | {f(r.get(key))} |")
    source = (m.get("hopf") or {}).get("reference_source")
    if source:
        lines += ["", f"Hopf and fold references: {source}."]
    lines += ["", "Points measured a hair from a fold are compared with the model's fold "
              "when that is nearer than any orbit at their parameter (see `ude-fit fit`'s "
              "error definitions).", "", "## What the mechanistic model was missing", ""]
    steps = loopm["steps"]
    if not steps:
        lines.append("The loop tried nothing: no candidate effect beat the noise.")
    for s in steps:
        name = s.get("name") or s.get("candidate")
        lines.append(f"- step {s['step']}: {name} — {'kept' if s['kept'] else 'not kept'} "
                     f"({s['reason']})")
    if loopm.get("effect"):
        e = loopm["effect"]
        lines += ["", f"Top effect: **{e['name']}** (`{e['key']}`): " + ", ".join(
            f"{t} = {c:.4g} ± {uu:.2g}" for t, c, uu in
            zip(e["terms"], e["coefficients"], e["uncertainty"])) + "."]
    lines += ["", "![residual against the states](loop/residuals.png)", "",
              "## Details", "",
              "- [fit/report.md](fit/report.md): the mechanistic identification, every UDE "
              "start and the adequacy check, phase portraits.",
              "- [loop/report.md](loop/report.md): the ranked candidates with bootstrap "
              "uncertainties, each step of the loop, before and after.", ""]
    return "\n".join(lines)
