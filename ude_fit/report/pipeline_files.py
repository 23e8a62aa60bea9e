"""The pipeline's folder: ``fit/`` (as ``ude-fit fit`` writes it), ``loop/`` (as ``ude-fit
loop``), and the summary: metrics.json, report.md and diagram.png (every model over the
data) with the headline figures."""

from __future__ import annotations

import os

from .files import write_json, write_text
from .fit_files import write_fit
from .loop_files import write_loop
from .pipeline_markdown import render_pipeline
from .plots import plot_diagram

# the figures of each model the summary sets side by side
_KEYS = ("branch_rms", "branch_rms_with_missed", "branch_max", "missed", "trajectory_rms",
         "hopf", "fold")


def _pick(m: dict | None) -> dict | None:
    return None if m is None else {k: m.get(k) for k in _KEYS}


def write_pipeline(out, ds, result, provenance: dict) -> dict:
    """Write ``result`` (a :class:`~ude_fit.pipeline.PipelineResult` on ``ds``) into
    ``out``; returns the summary document written to metrics.json."""
    os.makedirs(out, exist_ok=True)
    opts = result.options
    fitm = write_fit(os.path.join(out, "fit"), ds, result.fit, provenance)
    loopm = write_loop(os.path.join(out, "loop"), ds, result.loop, provenance, name="loop",
                       options=opts.loop_json())

    diagrams = {"mechanistic": result.fit.diagrams["mechanistic"]}
    if result.fit.ude is not None:
        diagrams["UDE"] = result.fit.diagrams["ude"]
    if result.loop.added:
        diagrams["refined"] = result.loop.after.diagram
    plot_diagram(os.path.join(out, "diagram.png"), ds, diagrams,
                 title=f"{ds.system}: measured points, fitted and refined models")

    stable = sum(1 for o in ds if o.stable is True)
    unstable = sum(1 for o in ds if o.stable is False)
    before, after = loopm["before"], loopm["after"]
    headline = {
        "points": len(ds), "stable": stable, "unstable": unstable,
        "branch_error_before": before["branch_rms_with_missed"],
        "branch_error_after": after["branch_rms_with_missed"],
        "missed_before": before["missed"], "missed_after": after["missed"],
        "ude_branch_error": (fitm["ude"] or {}).get("branch_rms_with_missed"),
        "adequate_starts": f"{fitm['starts']['adequate']}/{opts.fit.starts}",
        "effects_added": [s.get("name") for s in loopm["steps"] if s.get("kept")],
    }
    doc = {
        **provenance,
        "options": opts.to_json(),
        "system": ds.system,
        "data": {"points": len(ds), "stable": stable, "unstable": unstable,
                 "sources": list(ds.sources),
                 "parameter_range": [min(o.parameter for o in ds),
                                     max(o.parameter for o in ds)]},
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
    write_json(os.path.join(out, "metrics.json"), doc)
    write_text(os.path.join(out, "report.md"), render_pipeline(doc, fitm, loopm))
    return doc
