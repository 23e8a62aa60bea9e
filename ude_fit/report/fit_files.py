"""A fit's folder: metrics.json, report.md, the diagram and phase-portrait figures and the
fitted models (what ``ude-fit fit`` writes, and ``fit/`` of ``ude-fit pipeline``)."""

from __future__ import annotations

import os

from ..model_file import save_model
from .files import write_json, write_text
from .markdown import render
from .plots import plot_diagram, plot_phase_portraits


def write_fit(out, ds, res, provenance: dict) -> dict:
    """Write ``res`` (a :class:`~ude_fit.fitting.FitResult` on ``ds``) into the folder
    ``out`` (created); returns the metrics document written to metrics.json."""
    os.makedirs(out, exist_ok=True)
    opts = res.options.to_json()
    metrics = {**res.to_json(), **provenance, "options": opts}
    meta = dict(options=opts, sources=list(ds.sources), scales=res.scales,
                ranges=res.ranges, version=provenance["version"],
                written=provenance["written"])
    save_model(os.path.join(out, "mechanistic.eqx"), res.mechanistic, role="mechanistic",
               diagram=res.diagrams["mechanistic"].to_json(), **meta)
    if res.ude is not None:
        save_model(os.path.join(out, "ude.eqx"), res.ude, role="ude",
                   diagram=res.diagrams["ude"].to_json(), **meta)
    figures = _figures(out, ds, res)
    metrics["figures"] = figures
    metrics["models"] = {"mechanistic": "mechanistic.eqx",
                         "ude": "ude.eqx" if res.ude is not None else None,
                         "starts": _save_starts(out, res, meta)}
    write_json(os.path.join(out, "metrics.json"), metrics)
    write_text(os.path.join(out, "report.md"), render(metrics, figures))
    return metrics


def _save_starts(out, res, meta) -> dict:
    """Every trained start's model, with its own traced diagram, as ``starts/start_K.eqx``
    (the kept one included): what the report judges each start by can be redrawn or traced
    again with ``ude-fit diagram``, not only the kept model's. {start number: path}."""
    paths = {}
    for rec in res.starts:
        if rec.model is None or rec.diagram is None:
            continue                    # dropped: its training diverged
        rel = os.path.join("starts", f"start_{rec.start}.eqx")
        os.makedirs(os.path.join(out, "starts"), exist_ok=True)
        save_model(os.path.join(out, rel), rec.model, role=f"start {rec.start}",
                   diagram=rec.diagram.to_json(), adequate=rec.adequate, **meta)
        paths[str(rec.start)] = rel
    return paths


def _figures(out, ds, res) -> dict:
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
