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

_EXIT_USAGE = 2


class _Parser(argparse.ArgumentParser):
    def error(self, message):          # one line, exit 2
        self.exit(_EXIT_USAGE, f"{self.prog}: error: {message}\n")


class UsageError(Exception):
    pass


def _positive_int(name):
    def conv(s):
        try:
            v = int(s)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{name} must be an integer, not {s!r}") from None
        if v < 1:
            raise argparse.ArgumentTypeError(f"{name} must be at least 1, not {v}")
        return v
    return conv


def _finite_float(name):
    def conv(s):
        try:
            v = float(s)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{name} must be a number, not {s!r}") from None
        if v != v or v in (float("inf"), float("-inf")):
            raise argparse.ArgumentTypeError(f"{name} must be finite, not {s!r}")
        return v
    return conv


def _nonnegative_float(name):
    finite = _finite_float(name)

    def conv(s):
        v = finite(s)
        if v < 0:
            raise argparse.ArgumentTypeError(f"{name} must not be negative, not {s!r}")
        return v
    return conv


def _positive_float(name):
    finite = _finite_float(name)

    def conv(s):
        v = finite(s)
        if v <= 0:
            raise argparse.ArgumentTypeError(f"{name} must be positive, not {s!r}")
        return v
    return conv


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="ude-fit", description="Fit mechanistic and universal-differential-equation "
                "models to logged limit cycles, trace their bifurcation diagrams, and report.")
    p.add_argument("--version", action="version", version=f"ude-fit {_version()}")
    sub = p.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    sub.required = True

    f = sub.add_parser("fit", help="fit the mechanistic model and a UDE; write metrics, "
                       "report, diagrams and the fitted models")
    f.add_argument("data", nargs="+", metavar="DATA",
                   help="campaign HDF5 files, lee2020 .mat files, or folders of them")
    f.add_argument("--system", required=True, choices=("flutter", "oscillator"))
    f.add_argument("--approximator", default="nn", choices=("nn", "gp"),
                   help="the correction: a neural network (default) or a Gaussian process")
    f.add_argument("--training", default="periodic", choices=("trajectory", "periodic"),
                   help="NN loss: one-period trajectories from the measured states (the "
                   "paper's) or closed periodic orbits with stability labels (default)")
    f.add_argument("--mechanistic", default="equation", choices=("equation", "periodic"),
                   help="mechanistic identification: least squares on the equation error "
                   "(default), or that refined by output error on the periodic orbits")
    f.add_argument("--starts", type=_positive_int("--starts"), default=5,
                   help="random starts; the best adequate one is kept (default 5)")
    f.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    f.add_argument("--width", type=_positive_int("--width"), default=12,
                   help="hidden units per layer of the NN (default 12)")
    f.add_argument("--depth", type=_positive_int("--depth"), default=2,
                   help="hidden layers of the NN (default 2)")
    f.add_argument("--weight-decay", type=_nonnegative_float("--weight-decay"), default=0.0,
                   metavar="W", help="periodic training: penalty on the mean square network "
                   "weight, for smoother corrections on few noisy points (default 0)")
    f.add_argument("--equilibrium-penalty", type=_nonnegative_float("--equilibrium-penalty"),
                   metavar="W", help="aerofoil: penalty on the correction's value and slope at "
                   "the equilibrium over the airspeed range, which holds the Hopf point (default 0)")
    f.add_argument("--smoothness-penalty", type=_nonnegative_float("--smoothness-penalty"),
                   metavar="W", help="aerofoil: penalty on the correction's curvature in "
                   "airspeed and amplitude, against diagrams that snake (default 0)")
    f.add_argument("--rest-stability", type=_nonnegative_float("--rest-stability"),
                   default=0.0, metavar="W", help="aerofoil: penalty on any growth rate of the "
                   "equilibrium at the airspeeds where the data shows it stable (up to the "
                   "highest unstable orbit's), so the correction cannot move the Hopf point "
                   "below the measured orbits, and on any decay rate beyond the Hopf point "
                   "the shrinking unstable orbits point to (default 0)")
    f.add_argument("--energy-shape", type=_nonnegative_float("--energy-shape"),
                   default=0.0, metavar="W", help="aerofoil: penalty on a correction whose net "
                   "work per cycle over amplitude squared is not concave in amplitude squared "
                   "(along the measured orbits' shapes): at most one unstable and one stable "
                   "orbit per airspeed, against diagrams that snake in amplitude (default 0)")
    f.add_argument("--energy-rising", type=_nonnegative_float("--energy-rising"),
                   default=0.0, metavar="W", help="aerofoil: penalty on a model whose net work "
                   "per cycle over amplitude squared (mechanistic forces and correction, along "
                   "the measured orbits' shapes) does not rise with the airspeed, from just "
                   "below the measured airspeeds up: the orbits then lie on one curve "
                   "V(amplitude), against branches that turn back and isolas (default 0)")
    f.add_argument("--param-scale", type=_positive_float("--param-scale"), default=1.0,
                   metavar="F", help="the network's parameter input is standardised by F times "
                   "its spread in the data; larger F, slower variation with it (default 1)")
    f.add_argument("--param-dependence", default="input", choices=("input", "polynomial"),
                   help="how the NN correction depends on the bifurcation parameter: as an "
                   "input like the states (default), or as a polynomial in it "
                   "(--param-degree) with state-dependent coefficients, which cannot wiggle "
                   "in it (the airspeed enters quasi-steady aerodynamics as V and V^2)")
    f.add_argument("--param-degree", type=_positive_int("--param-degree"), default=2,
                   metavar="D", help="--param-dependence polynomial: the degree (default 2)")
    f.add_argument("--reference-hopf", type=_finite_float("--reference-hopf"), metavar="V",
                   help="known Hopf airspeed (m/s) for the error figures")
    f.add_argument("--reference-fold", type=_finite_float("--reference-fold"), metavar="V",
                   help="known fold airspeed (m/s) for the error figures")
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
    add_parsers(sub, (_positive_int, _nonnegative_float))
    from ._cli_pipeline import add_parser as add_pipeline
    add_pipeline(sub, (_positive_int, _finite_float, _nonnegative_float, _positive_float))
    from .sweep import add_sweep_parser
    add_sweep_parser(sub)
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
    from ._fit import FitOptions, diagram_to_dict, fit
    from ._io import save_model
    from ._train import TrainConfig

    out = _out_dir(args.out)
    ds = load(args.data, args.system)
    reference = {k: v for k, v in (("hopf", args.reference_hopf),
                                   ("fold", args.reference_fold)) if v is not None}
    if reference and args.system != "flutter":
        raise UsageError("--reference-hopf/--reference-fold apply to --system flutter only")
    if args.system != "flutter" and (args.equilibrium_penalty or args.smoothness_penalty
                                     or args.rest_stability or args.energy_shape
                                     or args.energy_rising):
        raise UsageError("--equilibrium-penalty/--smoothness-penalty/--rest-stability/"
                         "--energy-shape/--energy-rising apply to --system flutter only")
    if args.approximator != "nn" and (args.equilibrium_penalty or args.smoothness_penalty
                                      or args.rest_stability or args.energy_shape
                                      or args.energy_rising or args.param_scale != 1.0):
        raise UsageError("--equilibrium-penalty/--smoothness-penalty/--rest-stability/"
                         "--energy-shape/--energy-rising/"
                         "--param-scale apply to --approximator nn only")
    if args.approximator != "nn" and args.param_dependence != "input":
        raise UsageError("--param-dependence polynomial applies to --approximator nn only")
    opts = FitOptions(system=args.system, approximator=args.approximator,
                      training=args.training, starts=args.starts, seed=args.seed,
                      mechanistic=args.mechanistic,
                      train=TrainConfig(width=args.width, depth=args.depth,
                                        weight_decay=args.weight_decay,
                                        linear_weight=args.equilibrium_penalty,
                                        smooth_weight=args.smoothness_penalty,
                                        param_scale=args.param_scale,
                                        rest_weight=args.rest_stability,
                                        energy_weight=args.energy_shape,
                                        rising_weight=args.energy_rising,
                                        param_dependence=args.param_dependence,
                                        param_degree=args.param_degree))
    progress = _Progress(args.quiet)
    progress._say(f"{len(ds)} orbits loaded ({args.system}); fitting")
    res = fit(ds, opts, reference=reference or None, progress=progress)

    metrics = {**res.metrics, "version": _version(),
               "written": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
               "command": "ude-fit " + " ".join(shlex.quote(a) for a in argv),
               "inputs": _inputs(args.data), "options": opts.to_dict()}
    meta = dict(options=opts.to_dict(), sources=list(ds.sources), scales=res.scales,
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
        if args.command == "sweep":
            from .sweep import cmd_sweep
            return cmd_sweep(args)
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
