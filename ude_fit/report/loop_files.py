"""A loop's folder (``ude-fit refine``, ``ude-fit loop`` and ``loop/`` of ``ude-fit
pipeline``): metrics.json, report.md, the residual and before/after diagram figures, and
the mechanistic, refined and UDE models."""

from __future__ import annotations

import os

from ..discovery.loop import metrics_document
from ..model_file import save_model
from .files import write_json, write_text
from .loop_markdown import render_loop
from .plots import parameter_label, plot_diagram, plot_residuals, plot_shapes


def write_loop(out, ds, result, provenance: dict, *, name: str, options: dict) -> dict:
    """Write ``result`` (a :class:`~ude_fit.discovery.loop.LoopResult` on ``ds``) into
    ``out`` (created); returns the document written to metrics.json."""
    os.makedirs(out, exist_ok=True)
    system = ds.system
    doc = {**provenance, "command_name": name,
           "data": ds.record(), "options": options,
           **metrics_document(result)}
    figures = {}
    if result.explanations:
        plot_residuals(os.path.join(out, "residuals.png"), result.explanations[0],
                       parameter_label=parameter_label(system))
        figures["residual of the mechanistic model against the states"] = "residuals.png"
    if result.locations:
        plot_shapes(os.path.join(out, "shapes.png"), result.locations[0])
        figures["shape functions of single states (where the residual is)"] = "shapes.png"
    diagrams = {"mechanistic": result.before.diagram, "refined": result.after.diagram}
    for which in ("before", "after"):
        f = result.ude.get(which)
        if f is not None and f.ude is not None:
            diagrams[f"UDE on {'mechanistic' if which == 'before' else 'refined'}"] = \
                f.diagrams["ude"]
    plot_diagram(os.path.join(out, "diagram.png"), ds, diagrams,
                 title=f"{system}: before and after adding the effect")
    figures["bifurcation diagrams, before and after"] = "diagram.png"
    doc["figures"] = figures
    meta = dict(sources=list(ds.sources), ranges=result.ranges, version=doc["version"],
                written=doc["written"])
    save_model(os.path.join(out, "mechanistic.eqx"), result.before.model, role="mechanistic",
               scales=result.before.scales, diagram=result.before.diagram.to_json(),
               **meta)
    save_model(os.path.join(out, "refined.eqx"), result.after.model, role="refined",
               scales=result.after.scales, diagram=result.after.diagram.to_json(),
               **meta)
    models = {"mechanistic": "mechanistic.eqx", "refined": "refined.eqx"}
    for which, fname in (("before", "ude_mechanistic.eqx"), ("after", "ude_refined.eqx")):
        f = result.ude.get(which)
        if f is not None and f.ude is not None and (which == "before" or result.added):
            save_model(os.path.join(out, fname), f.ude, role=f"ude ({which})",
                       scales=f.scales, diagram=f.diagrams["ude"].to_json(), **meta)
            models[f"ude_{which}"] = fname
    doc["models"] = models
    write_json(os.path.join(out, "metrics.json"), doc)
    write_text(os.path.join(out, "report.md"), render_loop(doc, figures))
    return doc
