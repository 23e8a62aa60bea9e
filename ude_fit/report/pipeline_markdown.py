"""The pipeline's one summary page: the headline figures, the models side by side, and
what the loop found missing."""

from __future__ import annotations

from .._systems import system_kind
from .format import num, pct, short_location


def headline_text(h: dict) -> str:
    eff = ", ".join(h["effects_added"]) or "none"
    return (f"{h['points']} points ({h['stable']} stable, {h['unstable']} unstable); "
            f"branch error before {pct(h['branch_error_before'])}, after "
            f"{pct(h['branch_error_after'])} (added: {eff}); UDE {pct(h['ude_branch_error'])}, "
            f"{h['adequate_starts']} starts adequate")


def render_pipeline(doc: dict, fitm: dict, loopm: dict) -> str:
    h = doc["headline"]
    sysname = system_kind(doc["system"]).title
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
    kind = system_kind(doc["system"])
    lines += [f"{d['points']} periodic orbits, {kind.parameter_label} "
              f"{d['parameter_range'][0]:.4g} to {d['parameter_range'][1]:.4g} "
              f"{kind.parameter_unit}, from "
              + ", ".join(f"`{s}`" for s in d["sources"]) + ".", "",
              "## The models side by side", "",
              "| | mechanistic | UDE | refined (loop) |", "|---|---|---|---|"]
    m, u, r = doc["mechanistic"], doc["ude"] or {}, doc["refined"]
    rows = [("branch error, RMS (missed counted)", "branch_rms_with_missed", pct),
            ("branch error, max", "branch_max", pct),
            ("missed points", "missed", lambda x: num(x, "")),
            ("one-period trajectory error, RMS", "trajectory_rms", pct),
            ("Hopf (error)", "hopf", short_location),
            ("fold (error)", "fold", short_location)]
    if kind.forced:
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
