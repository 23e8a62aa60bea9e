"""The Markdown report of a fit: what was fitted to what, and the two models side by side."""

from __future__ import annotations

from .._systems import system_kind
from ..analysis.controlled import HeldSides
from ..analysis.keep import KeptStart
from .format import location, pct, sensor_zero_lines


def _ref(m: dict, key: str) -> str:
    e = (m or {}).get(key) or {}
    if e.get("reference") is None:
        return "no reference"
    return f"{e['reference']:.3f} ({e['reference_source']})"


def _kept_by(d: dict | None) -> str:
    """The sentence saying how the kept start was chosen (none for older files)."""
    return "" if d is None else " " + KeptStart.from_json(d).describe()


def _backbone(bb: dict | None, unit: str) -> list[str]:
    """The Hopf normal-form backbone fitted to the points (ude_fit.analysis.backbone)."""
    if bb is None:
        return []
    fold = ("no fold" if bb["fold"] is None else
            f"fold {bb['fold']:.3f} ± {bb['fold_std']:.3f} {unit}")
    return ["", f"Backbone (the Hopf normal form r' = r (m (V − V_H) + a r² + b r⁴) fitted to "
            f"the points alone, one Hopf point and at most one fold by construction): Hopf "
            f"{bb['hopf']:.3f} ± {bb['hopf_std']:.3f} {unit}, {fold}; branch amplitude error "
            f"RMS {pct(bb['branch_rms'])}, max {pct(bb['branch_max'])}, "
            f"{bb['missed']} missed."]


def _guides(g: dict | None, unit: str) -> list[str]:
    """The guide orbits the UDE trained on (ude_fit.training.guides), if any."""
    if not g:
        return []
    c = g["curve"]
    return ["", f"Guide orbits (`--guide-orbits`): {len(g['orbits'])} orbits of a curve with "
            f"one Hopf point and one fold fitted to the points (Hopf {c['hopf']:.3f} {unit}, "
            f"fold {c['fold']:.3f} {unit}; the points' amplitude error about it RMS "
            f"{pct(c['amplitude_rms'])}), their heave only, each at weight {g['weight']:g} "
            "against a measured orbit's 1. They shape the training only; every figure here "
            "is against the measured points."]


def _margins(sm: dict | None, points: list[dict], unit: str) -> list[str]:
    """The stability margins the UDE trained with, if from the backbone
    (ude_fit.analysis.margins): each labelled point's, or the constant where none."""
    if not sm:
        return []
    cells = []
    for p, m in zip(points, sm["points"]):
        if p.get("stable") is None:
            continue
        value = (f"{m['used']:.3f}" if m["used"] is not None
                 else f"{sm['floor']:g} (constant)")
        cells.append(f"{p['parameter']:.2f} {unit} {'stable' if p['stable'] else 'unstable'}"
                     f" {value}")
    return ["", "Stability margins (`--backbone-margins`: each labelled orbit's indicator as "
            "the backbone and its branch's straight line predict it, the smaller, with the "
            f"mechanistic model's growth-rate slope {sm['growth_rate_slope']:.4g} /s per "
            f"{unit}, one standard error towards neutral; the constant where they predict "
            "none and for each branch's orbit next to the fold): " + "; ".join(cells) + "."]


def _fold_cell(m: dict) -> str:
    """A start's fold count and, for a self-excited diagram, where each fold is
    (parameter @ amplitude in mm; "isola" for one on a closed branch of its own)."""
    pts = m.get("fold_points")
    if not isinstance(pts, list) or not pts:
        return str(m.get("fold_count", "—"))
    where = ", ".join(f"{f['param']:.2f} @ {1e3 * f['amplitude']:.1f}"
                      + (" (isola)" if f["isola"] else "") for f in pts)
    return f"{m['fold_count']}: {where}"


def _criticality_cell(r: dict) -> str:
    c = r.get("hopf_criticality")
    if not c:
        return "—"
    return f"{'sub' if c['subcritical'] else 'super'}, {1e6 * c['amplitude2_slope']:.4g}"


def _guide_rounds(records: list[dict]) -> list[str]:
    """What the guide rounds (ude_fit.guide_rounds) did to each start they ran on."""
    out = []
    for r in records:
        g = r.get("guide_rounds")
        if g is None:
            continue
        done = "; ".join(f"round {i} (weight {x['weight']:g}): {x['folds']} folds, "
                         f"{x['missed']} missed, {pct(x['branch_rms'])}"
                         + _newly_broken(x, g)
                         for i, x in enumerate(g["rounds"], 1)) or "no round ran"
        kept = ("the trained model (no round came nearer the rule without missing more "
                "points)"
                if g["kept_round"] == 0
                else f"round {g['kept_round']}'s model")
        stop = f" Stopped: {g['stop']}." if g.get("stop") else ""
        out.append(f"- start {r['start']}: {g['folds_before']} folds after training, "
                   f"{g['folds_allowed']} allowed, {g['missed_before']} missed; "
                   f"{done}. Kept {kept}; the table gives "
                   f"its figures.{stop}")
    if not out:
        return []
    return ["", "Guide rounds (`--guide-rounds`): the starts whose diagram had more folds "
            "than allowed, or missed a measured point, were trained on with orbits of the "
            "one-fold curve fitted to the points (docs/fitting.md):", "", *out]


def _constraint_rounds(records: list[dict]) -> list[str]:
    """What the constraint rounds (training.rounds.enforce_constraints) did to each start
    they ran on, and what holding the conditions cost the data's misfit (files from before
    the misfit was recorded give the rounds alone)."""
    out = []
    for r in records:
        info = r.get("info") or {}
        if not info.get("constraint_rounds"):
            continue
        broken = ", ".join(f"`--{c}`" for c in info.get("constraints_broken_before", []))
        weights = ", ".join(f"`--{k[:-len('_weight')]}` {v:.3g}" for k, v in info.items()
                            if k.endswith("_weight") and v)
        before, after = info.get("misfit_before_rounds"), info.get("misfit_after_rounds")
        cost = ("" if before is None or after is None or before <= 0 else
                f"; the data's misfit {before:.3g} → {after:.3g} ({after / before - 1:+.0%})")
        met = "all met" if info.get("constraints_met") else "not all met"
        out.append(f"- start {r['start']}: broke {broken or 'a condition'}; "
                   f"{info['constraint_rounds']} round(s), final weights {weights}, "
                   f"{met}{cost}.")
    if not out:
        return []
    return ["", "Constraint rounds: the starts whose trained model broke a condition of the "
            "physics (docs/fitting.md) trained on with it weighted from the data's misfit; "
            "the misfit is the periodic objective without the conditions, before the first "
            "round and after the last:", "", *out]


def _newly_broken(r: dict, g: dict) -> str:
    """The constraint conditions a guide round's model breaks that the trained one met."""
    new = [c for c in r.get("constraints_broken", [])
           if c not in g.get("constraints_broken_before", [])]
    return f", breaks {', '.join(f'`--{c}`' for c in new)}" if new else ""


def _unknown_stability(d: dict) -> list[str]:
    unknown = d.get("unknown_stability") or []
    if not unknown:
        return []
    return [f"{len(unknown)} point(s) of unknown stability (no `--stability` rule, no "
            "campaign label, no `CBC_stable_`/`CBC_unstable_`/`CBC_v` name): "
            + ", ".join(f"`{s}`" for s in unknown) + ". They still constrain the orbit's "
            "shape in the fit; the stability checks (training and the adequacy test) skip "
            "them.", ""]


def _holding(d: dict, control: dict | None) -> list[str]:
    """The holding control's invasiveness per point (data/holding.py); with the control as
    a known input, also its force against the heave spring's (training/control.py)."""
    points = d.get("point_records", [])
    if not any(r.get("holding") for r in points):
        return []
    spring = (control or {}).get("against_heave_stiffness")
    L = ["### Holding control", "",
         "How invasive the control that held each point was: its first harmonic (in the "
         "channel's unit) and that in standard errors of the same channel's noise, that "
         "relative to the response scaled by the controller's gains (where known), and the "
         "target's first harmonic against the response's. *Invasive*: a control fundamental "
         "more than 3 standard errors from zero."
         + ("" if spring is None else
            f" With the control as an input (gain {control['gain']:.4g} N per "
            f"{control['unit']}, {control['gain_source']}): its force's fundamental against "
            "the heave spring's, k_h times the heave fundamental (k_h of the mechanistic "
            "model identified with it)."), "",
         "| point | parameter | control 1st harmonic | in standard errors | "
         "relative to gains x response | target vs response | invasive |"
         + ("" if spring is None else " against the heave spring |"),
         "|---|---|---|---|---|---|---|" + ("" if spring is None else "---|")]
    for k, r in enumerate(points):
        h = r.get("holding")
        if not h:
            continue
        rel = h["control_relative_to_gains"]
        L.append(f"| `{r['source']}` | {r['parameter']:.4g} | {h['control_amplitude']:.3g} "
                 f"{h['control_unit']} | {h['control_significance']:.3g} | "
                 f"{'—' if rel is None else pct(rel)} | {pct(h['target_mismatch'])} | "
                 f"{'yes' if h['invasive'] else 'no'} |"
                 + ("" if spring is None else f" {pct(spring[k])} |"))
    return L + [""]


def _held_sides(ude: dict | None) -> list[str]:
    """With the control as an input: where the invasive points lie against the kept UDE's
    open-loop orbits, and a warning for a branch held on one side only
    (analysis/controlled.py, HeldSides)."""
    sides = ((ude or {}).get("controlled") or {}).get("held_sides")
    if not sides:
        return []
    counts = "; ".join(f"{b}: {sides['above'][b]} above, {sides['below'][b]} below"
                       for b in ("stable", "unstable"))
    warning = HeldSides(sides["above"], sides["below"]).warning()
    return [f"Invasive points against the kept UDE's open-loop orbits at their airspeeds: "
            f"{counts}." + (f" {warning}" if warning else ""), ""]


def _controlled_rows(mech: dict, ude: dict | None) -> list[str]:
    """With the control as an input: both models' orbits under the recorded control
    against the points, and the figures the adequacy judged (analysis/controlled.py)."""
    if not mech.get("controlled"):
        return []
    c = lambda m: (m or {}).get("controlled") or {}
    n = lambda x: "—" if x is None else str(x)
    return [f"| orbits under the recorded control: amplitude error, RMS | "
            f"{pct(c(mech).get('branch_rms'))} | {pct(c(ude).get('branch_rms'))} |",
            f"| orbits under the recorded control: missed (no closed orbit) | "
            f"{n(c(mech).get('missed'))} | {n(c(ude).get('missed'))} |",
            f"| judged (under the control, where the diagram has the point's stability): "
            f"RMS, missed | {_judged_cell(c(mech))} | {_judged_cell(c(ude))} |"]


def _judged_cell(c: dict | None) -> str:
    j = (c or {}).get("judged")
    return "—" if not j else f"{pct(j['branch_rms'])}, {j['missed']}"


def _judged_by_control(mech: dict) -> list[str]:
    if not mech.get("controlled"):
        return []
    return ["With the recorded control as a known input, the errors this check compares "
            "are those of each model's orbits under the control at the measured points "
            "(the points are orbits of the controlled system); a point counts as met where "
            "that orbit closes and the diagram has an orbit of the point's stability there "
            "(the stability is the open-loop system's). The table's first columns are the "
            "open-loop diagram's; the last, what was judged.", ""]


def render(metrics: dict, figures: dict) -> str:
    """Markdown text from ``metrics`` (as written to metrics.json) and figure file names."""
    mech, ude = metrics["mechanistic"], metrics.get("ude")
    kind = system_kind(metrics["system"])
    sysname, unit = kind.title, kind.parameter_unit
    d = metrics["data"]
    L = [f"# ude-fit report: {sysname}", "",
         f"Written by ude_fit {metrics['version']} on {metrics['written']}; "
         f"command `{metrics['command']}`.", "",
         "## Data", "",
         f"{d['points']} periodic orbits ({d['stable']} stable, {d['unstable']} unstable, "
         f"{d['points'] - d['stable'] - d['unstable']} of unknown stability) from "
         + ", ".join(f"`{s}`" for s in d["sources"]) + ".",
         f"Largest measured amplitude {1e3 * d['max_amplitude']:.3f} mm; amplitude errors are "
         "relative to it.", ""] + _unknown_stability(d) + sensor_zero_lines(d) + _holding(
            d, mech.get("identification", {}).get("control")) + _held_sides(ude) + [
         "## Models side by side", "",
         f"UDE: {metrics['approximator'].upper()} correction, training `{metrics['training']}`, "
         f"start {ude['start'] if ude else '—'} of {metrics['starts']['requested']} kept."
         + _kept_by(metrics["starts"].get("kept_by")), "",
         "| | mechanistic | UDE |", "|---|---|---|"]
    g = lambda k: (mech.get(k), (ude or {}).get(k))
    rows = [("branch amplitude error, RMS", pct), ("branch amplitude error, max", pct),
            ("missed points", lambda x: "—" if x is None else str(x)),
            ("one-period trajectory error, RMS", pct)]
    keys = ["branch_rms", "branch_max", "missed", "trajectory_rms"]
    for (label, f), k in zip(rows, keys):
        a, b = g(k)
        L.append(f"| {label} | {f(a)} | {f(b)} |")
    L += _controlled_rows(mech, ude)
    if kind.autonomous:
        L.append(f"| Hopf airspeed ({unit}) | {location(mech.get('hopf'))} | "
                 f"{location((ude or {}).get('hopf'))} |")
        L.append(f"| fold airspeed ({unit}) | {location(mech.get('fold'))} | "
                 f"{location((ude or {}).get('fold'))} |")
        L += ["", f"References: Hopf {_ref(mech, 'hopf')}, fold {_ref(mech, 'fold')}."]
        for name, mm in (("mechanistic", mech), ("UDE", ude or {})):
            if mm.get("isolas"):
                L.append(f"The {name} model also has {mm['isolas']} branch(es) not connected "
                         "to its Hopf point (traced from the measured orbits it passes near)"
                         + (f", with folds at {', '.join(f'{x:.3f}' for x in mm['isola_folds'])}"
                            if mm.get("isola_folds") else "") + ".")
        L += _backbone(metrics.get("backbone"), unit)
        L += _guides(metrics.get("guides"), unit)
        L += _margins(metrics.get("stability_margins"),
                      metrics.get("data", {}).get("point_records", []), unit)
    else:
        L += ["", "### Per forcing frequency", "",
              "| frequency (Hz) | mechanistic RMS | UDE RMS | mechanistic max | UDE max | "
              "missed (mech / UDE) | folds, mechanistic | folds, UDE |",
              "|---|---|---|---|---|---|---|---|"]
        for f, mm in mech.get("per_frequency", {}).items():
            uu = (ude or {}).get("per_frequency", {}).get(f, {})
            fm = ", ".join(f"{x:.4g}" for x in mech.get("folds", {}).get(f, [])) or "none"
            fu = ", ".join(f"{x:.4g}" for x in (ude or {}).get("folds", {}).get(f, [])) or "none"
            L.append(f"| {f} | {pct(mm['branch_rms'])} | {pct(uu.get('branch_rms'))} | "
                     f"{pct(mm['branch_max'])} | {pct(uu.get('branch_max'))} | "
                     f"{mm['missed']} / {uu.get('missed', '—')} | {fm} | {fu} |")
    st = metrics["starts"]
    L += ["", "## Starts and the adequacy check", "",
          f"{st['adequate']} of {st['requested']} starts adequate ({st['completed']} completed, "
          f"{len(st['dropped'])} dropped). A start is adequate when it misses no measured point "
          "(an orbit with the measured stability at every measured parameter), its branch RMS "
          + ("error is below the backbone's (the mechanistic model has no orbit at any "
             "point, so no error to beat; the backbone's is "
             f"{pct((metrics['backbone'] or {}).get('branch_rms'))}), "
             if st["criterion"].get("below_backbone") else
             "error is below the mechanistic model's, ")
          + f"and within "
          f"{st['criterion']['factor_of_best']} times that of the best start passing the "
          f"other checks (or under {pct(st['criterion']['floor'])}, or under the data's own "
          f"scatter about smooth branches, {pct(st['criterion']['data_scatter'])}).",
          "",
          "A start must also be qualitatively the mechanistic model's diagram: at most one "
          "fold more per branch family (one family for the aerofoil, one per frequency for "
          "the oscillator)"
          + ("; and, as the data has stable and unstable orbits, at least one fold (the "
             "branch from the Hopf point turns there to become the stable one)."
             if st["criterion"].get("fold_required") else "."), "",
          *_judged_by_control(mech),
          "| start | status | seconds | branch RMS | max | missed | folds (at parameter @ mm) | "
          "Hopf | fold | adequate | Hopf criticality, dA²/dV |"
          + (" judged under the control: RMS, missed |" if mech.get("controlled") else ""),
          "|---|---|---|---|---|---|---|---|---|---|---|"
          + ("---|" if mech.get("controlled") else "")]
    for r in st["records"]:
        m = r.get("metrics") or {}
        L.append(f"| {r['start']} | {r['status']} | {r['seconds']:.1f} | "
                 f"{pct(m.get('branch_rms'))} | {pct(m.get('branch_max'))} | "
                 f"{m.get('missed', '—')} | {_fold_cell(m)} | "
                 f"{location(m.get('hopf'))} | {location(m.get('fold'))} | "
                 f"{'yes' if r.get('adequate') else 'no'} | {_criticality_cell(r)} |"
                 + (f" {_judged_cell(r.get('controlled'))} |" if mech.get("controlled")
                    else ""))
    slope = d.get("unstable_amplitude2_slope")
    if any(r.get("hopf_criticality") for r in st["records"]):
        L.append("\nHopf criticality: *sub* (unstable orbits where the equilibrium is stable) or "
                 "*super*, from the first Lyapunov coefficient at each start's Hopf point, and "
                 "the slope it gives the branch's squared heave amplitude there (mm² per "
                 f"{unit}); the data's smaller unstable orbits: "
                 + ("no line" if slope is None else f"{1e6 * slope:.4g}") + ".")
    offsets = [(r["start"], r["info"]["parameter_offsets"]) for r in st["records"]
               if (r.get("info") or {}).get("parameter_offsets") is not None]
    if offsets:
        L.append(f"\nParameter offsets (`--parameter-errors`; the points' scatter in {unit} "
                 f"about smooth branches, the prior's scale: {d['parameter_scatter']:.3g}): "
                 "where each start put every measured orbit, in file order, against its "
                 "logged value. " + "; ".join(
                     f"start {k}: " + ", ".join(f"{x:+.3g}" for x in off)
                     for k, off in offsets) + ".")
    for d_ in st["dropped"]:
        L.append(f"\nStart {d_['start']} dropped: {d_['reason']}.")
    L += _constraint_rounds(st["records"])
    L += _guide_rounds(st["records"])
    ident = mech.get("identification", {})
    sources, known = ident.get("sources", {}), ident.get("known", {})
    L += ["", "## Mechanistic parameters", "",
          f"Method: {ident.get('method', 'given')}.", "",
          "| parameter | value | standard error | from |", "|---|---|---|---|"]
    for k, v in mech["parameters"].items():
        L.append(f"| {k} | {v:.6g} | {mech['std_error'].get(k, float('nan')):.2g} | "
                 f"{sources.get(k, '—')} |")
    for k, src in sources.items():
        if k not in mech["parameters"]:
            L.append(f"| {k} | {known.get(k, float('nan')):.6g} | — | {src} |")
    L += ["", "## Figures", ""]
    for label, name in figures.items():
        L.append(f"![{label}]({name})")
        L.append("")
    L += ["## Points", "",
          f"| parameter ({unit}) | frequency (Hz) | stable | measured (mm) | mechanistic (mm) | "
          "UDE (mm) |", "|---|---|---|---|---|---|"]
    up = {(p["parameter"], p["frequency"], p["measured"]): p for p in (ude or {}).get("points", [])}
    for p in mech["points"]:
        q = up.get((p["parameter"], p["frequency"], p["measured"]), {})
        mm = lambda x: "missed" if x is None else f"{1e3 * x:.3f}"
        st_ = {True: "yes", False: "no", None: "?"}[p["stable"]]
        L.append(f"| {p['parameter']:.4g} | {p['frequency']:.4g} | {st_} | "
                 f"{1e3 * p['measured']:.3f} | {mm(p['model'])} | {mm(q.get('model'))} |")
    return "\n".join(L) + "\n"
