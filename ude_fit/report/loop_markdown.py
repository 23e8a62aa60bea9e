"""Markdown reports of ``ude-fit explain`` and of ``ude-fit refine`` / ``ude-fit loop``."""

from __future__ import annotations

from .._systems import system_kind
from ..discovery.explain import EQUATIONS
from .format import location, pct, sensor_zero_lines


def _g(x, fmt=".4g") -> str:
    return "—" if x is None else format(x, fmt)


def _coefs(e: dict) -> str:
    unc = e.get("uncertainty") or [None] * len(e["coefficients"])
    return "; ".join(f"{t}: {_g(c)} ± {_g(u, '.2g')}"
                     for t, c, u in zip(e["terms"], e["coefficients"], unc))


def _shape(e: dict) -> str:
    return "" if e.get("shape") is None else f"{e['shape_name']} = {_g(e['shape'])}"


def candidates_section(ex: dict, system: str) -> list[str]:
    """The ranked candidates of one explanation, and each equation's selection path."""
    L = [f"**{ex['summary']}.**", "",
         "| rank | effect | kind | equation | coefficients (± bootstrap s.d.) | shape | "
         "share of residual | share of force |", "|---|---|---|---|---|---|---|---|"]
    for i, e in enumerate(ex["ranked"], 1):
        L.append(f"| {i} | {e['name']} (`{e['key']}`) | {e['kind']} | "
                 f"{EQUATIONS[system][e['equation']]} | {_coefs(e)} | {_shape(e)} | "
                 f"{100 * e['share']:.1f} % | {100 * e['force_share']:.3f} % |")
    if not ex["ranked"]:
        L.append("| — | no candidate lowers the cross-validated error by more than its "
                 "standard error | | | | | | |")
    L.append("")
    for q in ex["equations"]:
        path = ", ".join(f"{p['added'] or 'mechanistic'} {p['cv_mse']:.3g}"
                         for p in q["cv_path"])
        L.append(f"- {EQUATIONS[system][q['equation']]}: mechanistic residual "
                 f"{100 * q['residual_rms'] / q['force_rms']:.2f} % of the force RMS; "
                 f"cross-validated error along the forward path: {path}.")
    L.append("")
    return L


METHOD = [
    "Method: the mechanistic model is fitted by least squares on the equation error of the "
    "averaged orbits; its residual is regressed on physically named candidates (the "
    "mechanistic columns always in), chosen by forward selection scored by leave-orbits-out "
    "cross-validation with the one-standard-error rule; shape parameters (freeplay gap, lag "
    "time constant) by the same CV error; uncertainty by a bootstrap over orbits. Effects of "
    "the wrong physical sign (friction or damping that feeds energy in) are not admitted. "
    "Structural effects are ranked before linear, parameter-dependent terms, which describe "
    "mismatch of the linear model (for the aerofoil: the unsteady aerodynamics the "
    "quasi-steady model leaves out) rather than missing physics.", ""]


def control_line(control: dict | None, refined: dict | None = None) -> list[str]:
    """The sentence that says the recorded control was a known input, and its gain (and
    the ``refined`` model's, identified with it, where that differs)."""
    if not control:
        return []
    also = ""
    if refined and refined["gain"] != control["gain"]:
        also = f"; with the refined model's terms {refined['gain']:.4g}"
    return [f"The recorded holding control is a known heave force in every identification "
            f"and residual (gain {control['gain']:.4g} N per {control['unit']}, "
            f"{control['gain_source']}{also}): a point held with some control is read as an "
            "orbit of the controlled system.", ""]


def render_explain(doc: dict, figures: dict) -> str:
    ex = doc["explanation"]
    L = [f"# ude-fit explain: {doc['system']}", "",
         f"Written by ude_fit {doc['version']} on {doc['written']}; command "
         f"`{doc['command']}`.", "",
         f"{doc['data']['points']} orbits from " + ", ".join(f"`{s}`" for s in
                                                           doc["data"]["sources"]) + ".", ""]
    L += sensor_zero_lines(doc["data"])
    L += control_line(doc.get("control"))
    L += [f"## Residual of the {doc['what']}", ""]
    L += candidates_section(ex, doc["system"])
    L += METHOD
    for title, f in figures.items():
        L += [f"## {title[0].upper() + title[1:]}", "", f"![{title}]({f})", ""]
    return "\n".join(L)


def _row(label, f, key, cols) -> str:
    return f"| {label} | " + " | ".join(f((c or {}).get(key)) for c in cols) + " |"


def location_section(where: dict) -> list:
    """Where the residual is: the significant shapes of single states and what they are."""
    L = ["", "## Where the residual is: shapes of single states", "",
         f"{where['summary']}. Penalised splines of each state per equation (smoothness by "
         "leave-orbits-out cross-validation, F-type test at 1 % shared by an equation's "
         "shapes); each significant shape compared with generic classes and catalogue "
         "terms by BIC.", "", "| equation | state | p | share of residual | what | "
         "best class (BIC) | region |", "|---|---|---|---|---|---|---|"]
    for e in where["equations"]:
        for s in e["shapes"]:
            if not s["significant"]:
                continue
            d = s.get("description") or {}
            L.append(f"| {e['equation']} | {s['state']} | {s['p_value']:.2g} | "
                     f"{s['share']:.0%} | {d.get('phrase', '—')} | {d.get('shape_class', '—')}"
                     f" | {d.get('region', s['region'])} |")
    return L + [""]


def routes_section(routes: dict) -> list:
    """The residual route beside the UDE route (the learnt correction located and named
    the same way), and whether they agree."""
    L = ["", "## Two routes: the residual and the UDE's learnt correction", "",
         routes["summary"], "",
         "| route | located (equation, state) | shape | catalogue's top term |",
         "|---|---|---|---|"]
    for r in (routes["residual"], routes["ude"]):
        where = "nothing beyond the noise" if r["equation"] is None else \
            f"{r['equation']}, {r['state']}"
        named = "—" if r["catalogue_key"] is None else \
            f"{r['catalogue_name']} (`{r['catalogue_key']}`)"
        L.append(f"| {r['route']} | {where} | {r['description'] or '—'} | {named} |")
    L += ["", "The UDE's correction (on the mechanistic model) is evaluated on the measured "
          "orbits' samples and located by the same shape functions as the residual; "
          "agreement is on the equation and state of each route's strongest significant "
          "shape."]
    return L


def render_loop(doc: dict, figures: dict) -> str:
    b, a = doc["before"], doc["after"]
    ub, ua = b.get("ude"), a.get("ude")
    cols = [b, a] + ([ub, ua] if ub or ua else [])
    names = ["mechanistic (before)", "refined (after)"] + (
        ["UDE on mechanistic", "UDE on refined"] if ub or ua else [])
    eff = doc["effect"]
    L = [f"# ude-fit {doc['command_name']}: {doc['system']}", "",
         f"Written by ude_fit {doc['version']} on {doc['written']}; command "
         f"`{doc['command']}`.", "",
         f"{doc['data']['points']} orbits from " + ", ".join(f"`{s}`" for s in
                                                           doc["data"]["sources"]) + ".", ""]
    L += sensor_zero_lines(doc["data"])
    L += control_line((b.get("identification") or {}).get("control"),
                      (a.get("identification") or {}).get("control"))
    if eff:
        L += [f"**Effect added: {eff['name']}** (`{eff['key']}`, {eff['kind']}), "
              f"{eff['equation']} equation: {_coefs(eff)}"
              + (f"; {_shape(eff)}" if eff.get("shape") is not None else "") + ".", "",
              f"It depends on {', '.join(eff.get('states') or ['—'])}: "
              f"{eff.get('description', eff['name'])} (class: {eff.get('shape_class')}; "
              f"acts in {eff.get('region')}).", ""]
        others = [d for d in doc["added"][1:]]
        if others:
            L += ["Also kept, in order: " + ", ".join(f"`{d['key']}`" for d in others)
                  + ".", ""]
    else:
        L += ["**No effect added**: " + (doc["steps"][-1]["reason"] if doc["steps"] else
                                         "nothing to add") + ".", ""]
    L += ["## Before and after", "", "| | " + " | ".join(names) + " |",
          "|---|" + "---|" * len(names),
          _row("branch amplitude error, RMS", pct, "branch_rms", cols),
          _row("branch amplitude error, RMS counting missed points", pct,
               "branch_rms_with_missed", cols),
          _row("branch amplitude error, max", pct, "branch_max", cols),
          _row("missed points", lambda x: "—" if x is None else str(x), "missed", cols),
          _row("one-period trajectory error, RMS", pct, "trajectory_rms", cols)]
    if b.get("controlled"):
        ctl = [c.get("controlled") if c is not None else None for c in cols]
        L.append("| orbits under the recorded control: amplitude error, RMS (what the loop "
                 "judges) | " + " | ".join(pct((c or {}).get("branch_rms")) for c in ctl)
                 + " |")
        L.append("| orbits under the recorded control: missed points | " + " | ".join(
            "—" if c is None else str(c["missed"]) for c in ctl) + " |")
    if system_kind(doc["system"]).autonomous:
        L.append(_row("Hopf airspeed (m/s)", location, "hopf", cols))
        L.append(_row("fold airspeed (m/s)", location, "fold", cols))
    else:
        for f in sorted((b.get("per_frequency") or {}), key=float):
            L.append(f"| branch RMS at {f} Hz | " + " | ".join(
                pct(((c or {}).get("per_frequency") or {}).get(f, {}).get("branch_rms"))
                for c in cols) + " |")
    L.append(_row("parameters", lambda x: "—" if x is None else str(x), "n_parameters", cols))
    L += ["", "A missed point is a measured orbit the model has no orbit of the measured "
          "stability for; the second row counts it as an error of its measured amplitude.",
          "", "## Steps", "", "| step | candidate | kind | kept | why | branch RMS | missed |",
          "|---|---|---|---|---|---|---|"]
    for s in doc["steps"]:
        m = s.get("metrics") or {}
        L.append(f"| {s['step']} | {s.get('name') or s.get('candidate') or '—'} | "
                 f"{s.get('kind', '—')} | {'yes' if s['kept'] else 'no'} | {s['reason']} | "
                 f"{pct(m.get('branch_rms'))} | {m.get('missed', '—')} |")
    if doc.get("location"):
        L += location_section(doc["location"])
    if doc.get("routes"):
        L += routes_section(doc["routes"])
    L += ["", "## Candidates for the mechanistic model's residual", ""]
    if doc.get("explanation"):
        L += candidates_section(doc["explanation"], doc["system"])
    for i, ex in enumerate(doc.get("explanations") or [], 2):
        L += [f"### Residual after step {i - 1}", ""]
        L += candidates_section(ex, doc["system"])
    L += METHOD
    L += ["## Parameters", "", "| parameter | before | after | after, bootstrap s.d. |",
          "|---|---|---|---|"]
    pa, pb = a.get("parameters") or {}, b.get("parameters") or {}
    sd = (a.get("identification") or {}).get("bootstrap_std") or {}
    for k in list(pb) + [k for k in pa if k not in pb]:
        L.append(f"| `{k}` | {_g(pb.get(k))} | {_g(pa.get(k))} | {_g(sd.get(k), '.2g')} |")
    L.append("")
    for title, f in figures.items():
        L += [f"## {title[0].upper() + title[1:]}", "", f"![{title}]({f})", ""]
    return "\n".join(L)
