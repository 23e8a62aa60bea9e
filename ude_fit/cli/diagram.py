"""``ude-fit diagram``: redraw (or re-trace) a fitted model's bifurcation diagram."""

from __future__ import annotations

import os

import numpy as np

from ..analysis.diagram import trace_diagram
from ..analysis.diagram_type import Diagram
from ..data import OrbitDataset, load
from ..model_file import _version, load_model
from ..report.files import write_json
from ..report.plots import plot_diagram
from .common import out_dir


def add_parser(sub) -> None:
    d = sub.add_parser("diagram", help="redraw (or re-trace) a fitted model's bifurcation "
                       "diagram")
    d.add_argument("model", metavar="MODEL", help="a model file written by `ude-fit fit`")
    d.add_argument("--data", nargs="+", metavar="DATA", help="measured points to draw over it")
    d.add_argument("--retrace", action="store_true",
                   help="trace the branches again instead of using the stored ones")
    d.add_argument("--out", metavar="DIR", help="output folder (default: the model's folder)")


def run(args, argv) -> int:
    model, header = load_model(args.model)
    ds = (load(args.data, header["system"]) if args.data
          else OrbitDataset(header["system"], (), ()))
    out = out_dir(args.out or os.path.dirname(os.path.abspath(args.model)))
    if args.retrace or not header.get("diagram"):
        diagram = trace_diagram(model, header["ranges"], np.asarray(header["scales"]))
    else:
        diagram = Diagram.from_json(header["diagram"])
    role = header.get("role", "model")
    stem = os.path.splitext(os.path.basename(args.model))[0]
    png = os.path.join(out, f"{stem}_diagram.png")
    plot_diagram(png, ds, {role: diagram}, title=f"{header['system']}: {role} model")
    write_json(os.path.join(out, f"{stem}_diagram.json"),
               {"model": os.path.abspath(args.model), "retraced": bool(args.retrace),
                "version": _version(), "diagram": diagram.to_json()})
    hopf = [b.hopf["param"] for b in diagram.values() if b.hopf]
    folds = [f["param"] for b in diagram.values() for f in b.folds]
    print(f"wrote {png}; branches {len(diagram)}, Hopf "
          f"{', '.join(f'{h:.4f}' for h in hopf) or 'none'}, folds "
          f"{', '.join(f'{x:.4f}' for x in folds) or 'none'}")
    return 0
