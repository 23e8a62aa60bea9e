"""``ude-fit``: fit mechanistic and UDE models to logged limit cycles, trace and report.

    ude-fit fit DATA... --system flutter|oscillator [--approximator nn|gp]
                [--training trajectory|periodic] [--starts N] [--seed S] --out DIR
    ude-fit diagram MODEL [--data DATA...] [--retrace] [--out DIR]
    ude-fit explain DATA... --system S [--model UDE.eqx] --out DIR
    ude-fit refine DATA... --system S --add EFFECT[=SHAPE]... [--ude] --out DIR
    ude-fit loop DATA... --system S [--max-effects N] [--min-gain G] [--ude] --out DIR
    ude-fit pipeline DATA... --system S [--starts N] --out DIR    (fit, loop, one summary)

User mistakes (a bad file, an empty dataset, a bad option) end with one line on stderr and
exit status 2; a fit in which every start diverged ends with status 1 after writing what
it has.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import hashlib
import json
import os
import shlex
import sys
import time

from ._cli_options import add_data_arguments, add_fit_arguments, fit_options

_EXIT_USAGE = 2


class _Parser(argparse.ArgumentParser):
    def error(self, message):          # one line, exit 2
        self.exit(_EXIT_USAGE, f"{self.prog}: error: {message}\n")


class UsageError(Exception):
    pass


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="ude-fit", description="Fit mechanistic and universal-differential-equation "
                "models to logged limit cycles, trace their bifurcation diagrams, and report.")
    p.add_argument("--version", action="version", version=f"ude-fit {_version()}")
    sub = p.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    sub.required = True

    f = sub.add_parser("fit", help="fit the mechanistic model and a UDE; write metrics, "
                       "report, diagrams and the fitted models")
    add_data_arguments(f)
    add_fit_arguments(f)
    f.add_argument("--out", required=True, metavar="DIR", help="output folder (created)")
    f.add_argument("--quiet", action="store_true", help="no progress on the terminal")

    d = sub.add_parser("diagram", help="redraw (or re-trace) a fitted model's bifurcation "
                       "diagram")
    d.add_argument("model", metavar="MODEL", help="a model file written by `ude-fit fit`")
    d.add_argument("--data", nargs="+", metavar="DATA", help="measured points to draw over it")
    d.add_argument("--retrace", action="store_true",
                   help="trace the branches again instead of using the stored ones")
    d.add_argument("--out", metavar="DIR", help="output folder (default: the model's folder)")

    from ._cli_loop import add_parsers
    add_parsers(sub)
    from ._cli_pipeline import add_parser as add_pipeline
    add_pipeline(sub)
    return p


def _version() -> str:
    from ._io import _version as v
    return v()


# ---------------------------------------------------------------------------------------
# progress
# ---------------------------------------------------------------------------------------

class _Progress:
    """Terminal progress: stages, and training loss/step/elapsed at most every 2 s."""

    def __init__(self, quiet: bool):
        self.quiet = quiet
        self.t0 = time.perf_counter()
        self.last = 0.0

    def _say(self, text):
        if not self.quiet:
            print(f"[{time.perf_counter() - self.t0:7.1f} s] {text}", file=sys.stderr, flush=True)

    def __call__(self, event, **kw):
        if event == "stage":
            self._say(kw["stage"])
        elif event == "model":
            m = kw["metrics"]
            self._say(f"{kw['which']} model: branch RMS {_pct(m['branch_rms'])}, missed "
                      f"{m['missed']}")
        elif event == "start":
            self._say(f"start {kw['start']}/{kw['starts']}")
        elif event == "train":
            now = time.perf_counter()
            if now - self.last >= 2.0 or kw.get("step") == kw.get("steps"):
                self.last = now
                who = f"start {kw['start']}" if kw["start"] else "identification"
                self._say(f"  {who} {kw['stage']} {kw['optimiser']} step "
                          f"{kw['step']}/{kw['steps']} loss {kw['loss']:.3e} "
                          f"({kw['elapsed']:.1f} s)")
        elif event == "step":
            r = kw["record"]
            self._say(f"step {r['step']}: {r.get('name') or r.get('candidate')} "
                      f"{'kept' if r['kept'] else 'not kept'} ({r['reason']})")
        elif event == "start_done":
            r = kw["record"]
            if r["status"] == "ok":
                m = r["metrics"]
                self._say(f"start {r['start']} done in {r['seconds']:.1f} s: branch RMS "
                          f"{_pct(m['branch_rms'])}, missed {m['missed']}")
            else:
                self._say(f"start {r['start']} dropped: {r['reason']}")


def _pct(x):
    return "—" if x is None else f"{100 * x:.2f} %"


# ---------------------------------------------------------------------------------------
# commands
# ---------------------------------------------------------------------------------------

def _inputs(paths) -> list:
    out = []
    for p in paths:
        rec = {"path": os.path.abspath(p)}
        if os.path.isfile(p):
            h = hashlib.sha256()
            with open(p, "rb") as fh:
                for chunk in iter(lambda: fh.read(1 << 20), b""):
                    h.update(chunk)
            rec.update(bytes=os.path.getsize(p), sha256=h.hexdigest())
        out.append(rec)
    return out


def _out_dir(path: str) -> str:
    if os.path.exists(path) and not os.path.isdir(path):
        raise UsageError(f"--out {path}: exists and is not a folder")
    try:
        os.makedirs(path, exist_ok=True)
    except OSError as exc:
        raise UsageError(f"--out {path}: cannot create ({exc.strerror})") from None
    return path


def _write_json(path, obj):
    from ._io import _jsonable
    tmp = path + ".tmp"
    with open(tmp, "w") as fh:
        json.dump(obj, fh, indent=2, default=_jsonable)
        fh.write("\n")
    os.replace(tmp, path)


def cmd_fit(args, argv) -> int:
    from ._data import load
    from ._fit import diagram_to_dict, fit
    from ._io import save_model

    try:
        opts = fit_options(args)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    out = _out_dir(args.out)
    ds = load(args.data, args.system)
    progress = _Progress(args.quiet)
    progress._say(f"{len(ds)} orbits loaded ({args.system}); fitting")
    res = fit(ds, opts, progress=progress)

    metrics = {**res.metrics, "version": _version(),
               "written": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
               "command": "ude-fit " + " ".join(shlex.quote(a) for a in argv),
               "inputs": _inputs(args.data), "options": opts.to_json()}
    meta = dict(options=opts.to_json(), sources=list(ds.sources), scales=res.scales,
                ranges=res.ranges, version=_version(), written=metrics["written"])
    save_model(os.path.join(out, "mechanistic.eqx"), res.mechanistic, role="mechanistic",
               diagram=diagram_to_dict(res.diagrams["mechanistic"]), **meta)
    if res.ude is not None:
        save_model(os.path.join(out, "ude.eqx"), res.ude, role="ude",
                   diagram=diagram_to_dict(res.diagrams["ude"]), **meta)
    figures = _figures(out, ds, res)
    metrics["figures"] = figures
    metrics["models"] = {"mechanistic": "mechanistic.eqx",
                         "ude": "ude.eqx" if res.ude is not None else None}
    _write_json(os.path.join(out, "metrics.json"), metrics)
    from ._report import render
    with open(os.path.join(out, "report.md"), "w") as fh:
        fh.write(render(metrics, figures))
    u = metrics["ude"]
    print(f"wrote {out}/: metrics.json, report.md, " + ", ".join(figures.values())
          + ", mechanistic.eqx" + (", ude.eqx" if u else ""))
    print(f"branch RMS error: mechanistic {_pct(metrics['mechanistic']['branch_rms'])}, "
          f"UDE {_pct(u['branch_rms']) if u else 'no model'}; adequate starts "
          f"{metrics['starts']['adequate']}/{opts.starts}")
    if res.ude is None:
        print("ude-fit: every start diverged; no UDE (see report.md)", file=sys.stderr)
        return 1
    return 0


def _figures(out, ds, res) -> dict:
    from ._plots import plot_diagram, plot_phase_portraits
    figs = {}
    plot_diagram(os.path.join(out, "diagram.png"), ds, dict(res.diagrams),
                 title=f"{ds.system}: measured points and model branches")
    figs["bifurcation diagram"] = "diagram.png"
    models = {"mechanistic": res.mechanistic}
    if res.ude is not None:
        models["ude"] = res.ude
    plot_phase_portraits(os.path.join(out, "phase_portraits.png"), ds, models,
                         dict(res.diagrams), scales=res.scales)
    figs["phase portraits"] = "phase_portraits.png"
    return figs


def cmd_diagram(args, argv) -> int:
    import numpy as np

    from ._fit import diagram_from_dict, diagram_to_dict, trace_diagram
    from ._io import load_model
    from ._plots import plot_diagram

    model, header = load_model(args.model)
    out = _out_dir(args.out or os.path.dirname(os.path.abspath(args.model)))
    from ._data import OrbitDataset, load
    ds = (load(args.data, header["system"]) if args.data
          else OrbitDataset(header["system"], (), ()))
    if args.retrace or not header.get("diagram"):
        diagram = trace_diagram(model, header["ranges"], np.asarray(header["scales"]))
    else:
        diagram = diagram_from_dict(header["diagram"])
    role = header.get("role", "model")
    stem = os.path.splitext(os.path.basename(args.model))[0]
    png = os.path.join(out, f"{stem}_diagram.png")
    plot_diagram(png, ds, {role: diagram}, title=f"{header['system']}: {role} model")
    _write_json(os.path.join(out, f"{stem}_diagram.json"),
                {"model": os.path.abspath(args.model), "retraced": bool(args.retrace),
                 "version": _version(), "diagram": diagram_to_dict(diagram)})
    hopf = [b.hopf["param"] for b in diagram.values() if b.hopf]
    folds = [f["param"] for b in diagram.values() for f in b.folds]
    print(f"wrote {png}; branches {len(diagram)}, Hopf "
          f"{', '.join(f'{h:.4f}' for h in hopf) or 'none'}, folds "
          f"{', '.join(f'{x:.4f}' for x in folds) or 'none'}")
    return 0


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(argv)
    from ._data import DataError
    try:
        if args.command == "fit":
            return cmd_fit(args, argv)
        if args.command == "diagram":
            return cmd_diagram(args, argv)
        from . import _cli_loop, _cli_pipeline
        return {"explain": _cli_loop.cmd_explain, "refine": _cli_loop.cmd_refine,
                "loop": _cli_loop.cmd_loop,
                "pipeline": _cli_pipeline.cmd_pipeline}[args.command](args, argv)
    except (UsageError, DataError) as exc:
        print(f"ude-fit: error: {exc}", file=sys.stderr)
        return _EXIT_USAGE
    except KeyboardInterrupt:
        print("ude-fit: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
