"""Closing the loop: explain the mechanistic residual, add the effect, refit, compare.

``refine`` adds named effects (library keys, see ``_library``) to the mechanistic model
as physical terms with their own coefficients, identifies everything again by least
squares (equation error), traces the refined model's diagram and puts the metrics next
to the mechanistic model's. ``close_loop`` decides what to add itself:

1. fit the mechanistic model, trace its diagram (the *before*);
2. explain its residual (``_explain.explain``): significant candidates, ranked;
3. add the top-ranked candidate, refit, re-trace; keep it only if the diagram improves
   (branch RMS error down by at least ``min_gain`` of its value, no more points missed,
   or fewer missed): an effect a statistical test likes but the dynamics do not need is
   not kept (with the control as an input, the model's orbits under the recorded control
   are compared with the points instead, where its diagram has an orbit of each point's
   stability, :mod:`~ude_fit.analysis.controlled`);
4. repeat 2-3 on the refined model's residual until nothing significant is left, the
   top candidate does not improve the diagram, or ``max_effects`` are in.

The first effect kept is *the* effect of the report (``metrics["effect"]``); every step
is recorded. Optionally a UDE is fitted on the mechanistic model and on the refined one.

With the recorded control as a known input (``control``, the aerofoil) every model is
identified on the data carrying the control force (its gain with it where unknown), and
every residual is taken with it: a point held with some control is an orbit of the
controlled system, and without it the control's force would be read as missing physics.
The rule that keeps an effect then compares each model's orbits under the recorded control
with the points (:attr:`Stage.judged`): the open-loop diagram is as far from such points as
the control moved them, whichever model is right about the open-loop system. Whether the
model has an orbit of each point's stability there is still read from its diagram.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field

import numpy as np

from ..analysis.controlled import ControlledOrbits, controlled_orbits, judged, yardstick
from ..analysis.diagram import _evaluate
from ..analysis.metrics_type import BranchSummary, ModelMetrics
from ..data.orbit import OrbitDataset
from ..fitting import fit, prepare
from ..mechanistic_stage import identify_mechanistic, identify_with_control, with_chosen_zero
from ..models.forms import state_parts
from ..models.library import LIBRARY, STRUCTURAL, effect, states_of
from ..models.refined import describe
from ..models.ude import UDE
from ..training.control import ControlChoice
from ..training.identify import TrainingData, augment, identify
from ..training.options import FitOptions
from .describe import VERY_STRONG, describe as describe_shapes, effect_fields
from .explain import choose_shape, explain
from .locate import Location, locate
from .routes import RouteComparison, compare_routes



@dataclass
class Stage:
    """One model of the loop: the model, its diagram and its metrics."""
    name: str
    model: UDE
    diagram: dict
    metrics: ModelMetrics
    identification: dict
    scales: np.ndarray
    n_parameters: int
    data: TrainingData      # what it was identified on, its residual taken on (control)
    # with the control as an input: the model's orbits under the recorded control
    controlled: ControlledOrbits | None = None

    @property
    def judged(self) -> BranchSummary:
        """What the loop's rule compares (branch error, missed points): where the control
        is an input, each point's orbit under the recorded control (a point held with
        control is off the open-loop diagram by what the control did) where the diagram
        has an orbit of the point's stability (:func:`~ude_fit.analysis.controlled.judged`),
        else the open-loop diagram's."""
        return judged(self.metrics, self.controlled).summary

    def brief(self) -> dict:
        """The figures a step's record keeps."""
        out = {**{k: v for k, v in self.metrics.summary.to_json().items()
                  if k != "branch_rms_with_missed"}, "n_parameters": self.n_parameters}
        if self.controlled is not None:
            out["controlled"] = {k: v for k, v in self.controlled.to_json().items()
                                 if k not in ("errors", "amplitudes")}
            out["judged"] = {"branch_rms": self.judged.branch_rms,
                             "missed": self.judged.missed}
        return out


@dataclass
class LoopResult:
    system: str
    before: Stage
    after: Stage
    added: list                       # [(key, shape)] kept, in order
    steps: list = field(default_factory=list)
    explanations: list = field(default_factory=list)   # Explanation per step
    locations: list = field(default_factory=list)      # Location per step (shapes)
    ude: dict = field(default_factory=dict)             # {"before": FitResult, "after": ...}
    routes: RouteComparison | None = None               # residual vs UDE correction
    samples: int = 32                                   # samples per orbit of the analysis
    ranges: dict = field(default_factory=dict)
    seconds: float = 0.0
    states: dict | None = None                          # the samples' states (library)
    control: ControlChoice | None = None                # the control as a known input

    @property
    def effect(self) -> dict | None:
        """The first kept effect, as metrics.json reports it."""
        if not self.added:
            return None
        d = describe(self.after.model.mech)[0]
        key = d["key"]
        std = self.after.identification.get("bootstrap_std", {})
        d["uncertainty"] = [std.get(f"{key}[{t}]") for t in d["terms"]]
        d["kind"] = effect(self.system, key).kind
        d.update(effect_fields(self.system, key, d["shape"], d["coefficients"],
                               self.locations, self.states))
        return d


def _n_parameters(model: UDE) -> int:
    import equinox as eqx
    import jax
    n = len(model.mech.fitted)
    if model.correction is not None:
        leaves = jax.tree_util.tree_leaves(eqx.filter(model.correction, eqx.is_inexact_array))
        n += int(sum(np.size(x) for x in leaves))
    return n


def _stage(name, model, ds, data, ranges, ref, ref_source, ident, control) -> Stage:
    scales = np.asarray(augment(data, model.mech).y_scale)
    diagram, m = _evaluate(model, ds, ranges, scales, ref, ref_source)
    controlled = None if control is None else controlled_orbits(model, data, ds)
    return Stage(name, model, diagram, m, ident, scales, _n_parameters(model), data,
                 controlled)


def _identify(ds, data, system, added, control, *, seed, bootstrap):
    """(the data the model was identified on, the model with the effects ``added``, the
    identification info): with ``control``, on the data carrying the control force, its
    gain identified with the rest where unknown."""
    if control is not None:
        data, mech, ident = identify_with_control(ds, data, control, effects=tuple(added),
                                                  bootstrap=bootstrap, seed=seed)
    else:
        mech, ident = identify(data, system, effects=tuple(added), bootstrap=bootstrap,
                               seed=seed)
    ident["method"] = "equation error (least squares)"
    if added:
        ident["effects"] = [k for k, _ in added]
    bad = mech.unphysical()
    if bad:
        ident["unphysical"] = bad
    return data, mech, ident


def _better(new, old, min_gain: float) -> bool:
    """Does ``new`` improve on ``old`` (:attr:`Stage.judged` of each) as the loop keeps an
    effect: fewer points missed, or as many and the branch error down by ``min_gain``."""
    if new.branch_rms is None:
        return False
    if new.missed < old.missed:
        return True
    if new.missed > old.missed or old.branch_rms is None:
        return False
    return new.branch_rms <= (1.0 - min_gain) * old.branch_rms


def _before(ds, data, system, ranges, ref, ref_source, seed, bootstrap, control) -> Stage:
    # as `ude-fit fit` does: least squares bounded to physical signs
    if control is not None:
        data, mech, ident = identify_with_control(ds, data, control, bootstrap=bootstrap,
                                                  seed=seed)
    else:
        mech, ident = identify_mechanistic(data, system, bootstrap=bootstrap, seed=seed)
    return _stage("mechanistic", UDE(mech), ds, data, ranges, ref, ref_source, ident,
                  control)


def _about_chosen_zero(ds: OrbitDataset, system: str, control: ControlChoice | None,
                       samples: int) -> OrbitDataset:
    """``ds`` about the sensors' zero a fit with the same control would choose, where no
    file recorded it and nobody has chosen it yet (a no-op otherwise): the loop then starts
    from the rest position the fit and the command line start from, also when the library
    is called directly on loaded wind-tunnel files."""
    return with_chosen_zero(ds, FitOptions(
        system, samples=samples, control_input=control is not None,
        control_gain=None if control is None else control.gain))


def refine(ds: OrbitDataset, system: str, add: list, *, reference=None, seed: int = 0,
           bootstrap: int = 200, samples: int = 32, progress=None,
           control: ControlChoice | None = None) -> LoopResult:
    """Add the effects ``add`` ([(key, shape or None)]; a missing shape is chosen by
    cross-validation) to the mechanistic model, refit, and compare diagrams (with
    ``control``, the recorded control as a known input: see the module's docstring)."""
    say = progress or (lambda **kw: None)
    t0 = time.perf_counter()
    ds = _about_chosen_zero(ds, system, control, samples)
    ds, data, ranges, ref, ref_source = prepare(ds, system, reference, samples)
    say(event="stage", stage="mechanistic model")
    before = _before(ds, data, system, ranges, ref, ref_source, seed, bootstrap, control)
    added = []
    for key, shape in add:
        if shape is None:
            shape = choose_shape(before.data, system, key, added=tuple(added), seed=seed)
        added.append((key, shape))
    say(event="stage", stage="refined model: " + ", ".join(k for k, _ in added))
    used, mech, ident = _identify(ds, data, system, added, control, seed=seed,
                                  bootstrap=bootstrap)
    after = _stage("refined", UDE(mech), ds, used, ranges, ref, ref_source, ident, control)
    ex = explain(before.data, system, seed=seed, bootstrap=bootstrap)
    return LoopResult(system, before, after, added, steps=[
        {"step": 1, "candidate": ", ".join(k for k, _ in added), "kept": True,
         "reason": "given with --add", "metrics": after.brief()}],
        explanations=[ex], ranges=ranges, seconds=time.perf_counter() - t0, samples=samples,
        control=control)


def close_loop(ds: OrbitDataset, system: str, *, max_effects: int = 3,
               min_gain: float = 0.1, reference=None, seed: int = 0, bootstrap: int = 200,
               samples: int = 32, locate_shapes: bool = True, progress=None,
               control: ControlChoice | None = None) -> LoopResult:
    """explain -> add the top-ranked effect -> refit, while it improves the diagram.

    With ``locate_shapes`` (the default) each step also locates the residual as shapes of
    single states (:mod:`.locate`), describes the strongest (:mod:`.describe`) and tries its
    form beside the catalogue's top candidate; the diagram decides, a generic class having
    to beat a catalogue term by ``min_gain`` (:func:`_margin`). When none of a step's
    candidates improves the diagram (or none is significant), a second stage locates each
    velocity's coefficient as a shape of a displacement (position-dependent damping) and
    tries the strongest. Without it the loop tries the catalogue's candidates only. With
    ``control`` the recorded control is a known input (the module's docstring)."""
    say = progress or (lambda **kw: None)
    t0 = time.perf_counter()
    ds = _about_chosen_zero(ds, system, control, samples)
    ds, data, ranges, ref, ref_source = prepare(ds, system, reference, samples)
    say(event="stage", stage="mechanistic model")
    before = _before(ds, data, system, ranges, ref, ref_source, seed, bootstrap, control)
    current, added, steps, explanations, locations = before, [], [], [], []
    S = states_of(data, system)
    compared = yardstick(control is not None)
    for step in range(1, max_effects + 1):
        say(event="stage", stage=f"explaining the residual (step {step})")
        ex = explain(current.data, system, added=tuple(added), seed=seed,
                     bootstrap=bootstrap)
        explanations.append(ex)
        catalogue = ex.top() if ex.significant else None
        located = None
        if locate_shapes:
            loc = describe_shapes(locate(current.data, system, added=tuple(added),
                                         seed=seed), S)
            locations.append(loc)
            located = _located_candidates(loc, system) + [_spline_candidate(loc)]
        candidates, why_tried = _distinct([catalogue, *(located or [])]), None
        if not candidates and locate_shapes:
            loc2, candidates = _coefficient_candidates(current.data, system, added, seed, S,
                                                       set())
            if candidates:
                locations[-1] = loc2
        if not candidates:
            # nothing beats the noise: a linear term may still be worth a try on the
            # diagram (kept only if it improves it); a structural effect never is
            top = ex.best_linear_term()
            if top is None:
                steps.append({"step": step, "candidate": None, "kept": False,
                              "reason": ex.summary + "".join(
                                  "; " + loc.summary() for loc in locations[-1:])})
                break
            why_tried = "not significant by cross-validation; a linear term tried on the diagram"
            candidates = [top]
        best, rejected = _try_candidates(candidates, added, current, data, system, ds,
                                         ranges, ref, ref_source, seed, bootstrap,
                                         min_gain, say, control)
        if locate_shapes and not _better(best[3].judged, current.judged, min_gain):
            # second stage: a damping whose coefficient depends on a displacement (c(h) h')
            # is no shape of one state. Fitted beside the single states it shares what
            # they explain, so it is tried only once they have failed on the diagram
            loc2, second = _coefficient_candidates(current.data, system, added, seed, S,
                                                   {c["key"] for c in candidates})
            if second:
                locations[-1] = loc2
                best2, rejected2 = _try_candidates(second, added, current, data, system, ds,
                                                   ranges, ref, ref_source, seed, bootstrap,
                                                   min_gain, say, control)
                # `best` does not improve the diagram enough to be kept (that is why the
                # second stage runs): one that does replaces it, else the better one is shown
                if (_better(best2[3].judged, current.judged, min_gain)
                        or _better(best2[3].judged, best[3].judged,
                                   _margin(best2[0], best[0], min_gain))):
                    rejected += [best] + rejected2
                    best = best2
                else:
                    rejected += [best2] + rejected2
        for cand, _, _, st in rejected:
            why = (f"does better on {compared}"
                   if not _better(st.judged, best[3].judged, 0.0) else
                   f"does as well on {compared} (within {min_gain:.0%}) with a name and no "
                   "more parameters")
            steps.append({"step": step, "candidate": cand["key"], "name": cand["name"],
                          "kind": cand["kind"], "shape": cand["shape"], "kept": False,
                          "significant": True, "reason": "another candidate of this "
                          f"step ({best[0]['key']}) {why}", "metrics": st.brief()})
        top, trial, ident, stage = best
        keep = _better(stage.judged, current.judged, min_gain)
        reason = (f"improves {compared}" if keep else
                  f"does not improve {compared} by {min_gain:.0%}")
        if why_tried:
            reason = f"{why_tried}; {reason}"
        if "unphysical" in ident:
            reason += f"; least-squares estimate unphysical ({ident['unphysical']})"
        steps.append({"step": step, "candidate": top["key"], "name": top["name"],
                      "kind": top["kind"], "shape": top["shape"], "kept": keep,
                      "significant": why_tried is None, "reason": reason,
                      "metrics": stage.brief()})
        say(event="step", record=steps[-1])
        if not keep:
            break
        added, current = trial, stage
    # nothing kept: "after" is the mechanistic model itself
    return LoopResult(system, before, current, added, steps=steps,
                      explanations=explanations, locations=locations, ranges=ranges,
                      seconds=time.perf_counter() - t0, states=S, samples=samples,
                      control=control)


def _coefficient_candidates(data, system, added, seed, S, exclude: set):
    """(the location with the velocities' displacement-dependent coefficients among the
    shapes, the top such shape's candidates not in ``exclude``)."""
    loc = describe_shapes(locate(data, system, added=tuple(added), seed=seed,
                                 damping_shapes=True), S)
    cands = [c for c in _located_candidates(loc, system, coefficient_shapes=True)
             if c["key"] not in exclude]
    return loc, cands


def _try_candidates(candidates, added, current, data, system, ds, ranges, ref, ref_source,
                    seed, bootstrap, min_gain, say, control):
    """Refit and re-trace with each candidate; (the best trial, the others). Only the
    trials that improve on ``current`` as the loop keeps an effect compete (all of them
    when none does); the first of those (the catalogue's top, when it is significant and
    good enough) is the incumbent, and :func:`_margin` says what a challenger must gain
    over it."""
    tried = []
    for cand in candidates:
        trial = added + [(cand["key"], cand["shape"])]
        say(event="stage", stage=f"refitting with {cand['name']}")
        used, mech, ident = _identify(ds, data, system, trial, control, seed=seed,
                                      bootstrap=bootstrap)
        tried.append((cand, trial, ident, _stage("refined", UDE(mech), ds, used, ranges,
                                                 ref, ref_source, ident, control)))
    pool = [t for t in tried if _better(t[3].judged, current.judged, min_gain)] or tried
    best = pool[0]
    for t in pool[1:]:
        if _better(t[3].judged, best[3].judged, _margin(t[0], best[0], min_gain)):
            best = t
    return best, [t for t in tried if t is not best]


def _margin(challenger: dict, incumbent: dict, min_gain: float) -> float:
    """The fraction of the incumbent's branch error a challenger must take off to replace
    it. A catalogue term explains with a name and no more parameters than a generic class
    (which adds at least its threshold or scale), so a generic class or the spline (many
    parameters) replaces a catalogue term only as the loop's own rule admits any addition
    (``min_gain``); so does a class the criterion could not tell from the catalogue term
    (a tie). Between candidates of the same origin the better on the diagram wins."""
    generic = challenger["kind"] == "located shape"
    catalogue_incumbent = incumbent["kind"] != "located shape"
    if challenger.get("spline") or challenger.get("tie") or (generic and catalogue_incumbent):
        return min_gain
    return 0.0


def _spline_candidate(loc: Location) -> dict | None:
    """The top located shape as a spline term, when no class or catalogue term describes
    it: the spline beats the best by very strong evidence (BIC)."""
    sig = loc.significant()
    if not sig or sig[0].description is None:
        return None
    d = sig[0].description
    if d.spline is None or d.spline.bic > d.best.bic - VERY_STRONG:
        return None
    return {"key": d.spline.key, "name": f"{d.phrase()}: the shape itself (spline of "
            f"{d.state})", "shape": d.spline.shape, "kind": "located shape", "spline": True}


def _located_candidates(loc: Location, system: str, coefficient_shapes: bool = False
                        ) -> list:
    """The top significant located shape's description as loop candidates: the contender
    named, and the one of the other origin (catalogue or class) it ties with by BIC.
    ``coefficient_shapes``: the top among the shapes that are a velocity's coefficient
    depending on a displacement (``h_dot(h)``) instead."""
    sig = loc.significant()
    if coefficient_shapes:
        sig = [s for s in sig if state_parts(s.state)[1] is not None]
    if not sig or sig[0].description is None:
        return []
    d = sig[0].description
    out = []
    for c, name in ((d.best, d.phrase()), (d.tie, None)):
        if c is None:
            continue
        out.append({"key": c.key, "name": name or f"{c.label} (tied by BIC with "
                    f"{d.best.label}) in {d.state}", "shape": c.shape,
                    "kind": effect(system, c.key).kind if c.catalogue else "located shape",
                    "located": d.to_dict(), "tie": name is None})
    return out


def _distinct(candidates: list) -> list:
    """The candidates that are there, each key once (the first kept)."""
    out, seen = [], set()
    for c in candidates:
        if c is not None and c["key"] not in seen:
            seen.add(c["key"])
            out.append(c)
    return out


def fit_udes(result: LoopResult, ds: OrbitDataset, opts, *, reference=None, progress=None,
             seed: int = 0, bootstrap: int = 200):
    """A UDE on the mechanistic model and one on the refined model (same options); the
    first UDE's learnt correction is located and named as the residual was (the two routes,
    :mod:`.routes`). With the loop's control input each UDE takes it too, at its stage's
    gain."""
    for which, stage in (("before", result.before), ("after", result.after)):
        if which == "after" and not result.added:
            result.ude["after"] = result.ude.get("before")
            continue
        result.ude[which] = fit_stage_ude(result, stage, ds, opts, reference=reference,
                                          progress=progress)
    compare_ude_route(result, result.ude["before"], seed=seed,
                      bootstrap=bootstrap, progress=progress)
    return result


def fit_stage_ude(result: LoopResult, stage: Stage, ds: OrbitDataset, opts, *,
                  reference=None, progress=None):
    """A UDE fitted on one of the loop's stages (its mechanistic or refined model, with
    ``opts``); with the loop's control input it takes the control too, at the gain that
    stage identified."""
    if result.control is not None:
        opts = dataclasses.replace(opts, control_input=True,
                                   control_gain=stage.identification["control"]["gain"])
    return fit(ds, opts, reference=reference, progress=progress, mechanistic=stage.model)


def compare_ude_route(result: LoopResult, ude_fit, *, seed: int = 0, bootstrap: int = 200,
                      progress=None):
    """``result.routes``: the UDE route (``ude_fit``, a fit on the loop's mechanistic model)
    beside the loop's residual route; nothing when no UDE with a correction was kept."""
    if ude_fit.ude is None or ude_fit.ude.correction is None:
        return result
    say = progress or (lambda **kw: None)
    say(event="stage", stage="locating the UDE's learnt correction")
    result.routes = compare_routes(
        result.before.data, result.system, ude_fit.ude, seed=seed, bootstrap=bootstrap,
        residual_location=result.locations[0] if result.locations else None,
        residual_explanation=result.explanations[0] if result.explanations else None)
    return result


def catalogue_keys(system: str) -> tuple:
    """Library keys of the effects that are structural nonlinearities (not linear or
    parameter-dependent linear terms)."""
    return tuple(e.key for e in LIBRARY[system] if e.kind == STRUCTURAL)


def metrics_document(result: LoopResult) -> dict:
    """The JSON-able summary: before, after, effect, steps, candidates."""
    def side(stage: Stage, ude_fit=None) -> dict:
        m = stage.metrics.to_json()
        points = m.pop("points")
        m.update(n_parameters=stage.n_parameters,
                 parameters=stage.identification.get("parameters", {}), points=points)
        m["effects"] = describe(stage.model.mech)
        m["controlled"] = None if stage.controlled is None else stage.controlled.to_json()
        m["identification"] = {k: v for k, v in stage.identification.items()
                               if k not in ("parameters",)}
        if ude_fit is not None:
            kept = ude_fit.kept
            m["ude"] = None if kept is None else {
                **kept.metrics.summary.to_json(), "hopf": kept.metrics.hopf.to_json(),
                "fold": kept.metrics.fold.to_json(),
                "n_parameters": _n_parameters(ude_fit.ude) if ude_fit.ude else None,
                "adequate_starts": ude_fit.adequate,
                "starts": ude_fit.options.starts}
        return m

    first = result.explanations[0] if result.explanations else None
    where = result.locations[0] if result.locations else None
    return {
        "location": where.to_dict() if where else None,
        "locations": [w.to_dict() for w in result.locations[1:]],
        "system": result.system,
        "before": side(result.before, result.ude.get("before")),
        "after": side(result.after, result.ude.get("after")),
        "effect": result.effect,
        "added": [{"key": k, "shape": s} for k, s in result.added],
        "steps": result.steps,
        "explanation": first.to_dict() if first else None,
        "explanations": [e.to_dict() for e in result.explanations[1:]],
        "ranges": result.ranges,
        "routes": None if result.routes is None else result.routes.to_json(),
        "seconds": result.seconds,
    }
