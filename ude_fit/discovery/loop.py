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
   not kept;
4. repeat 2-3 on the refined model's residual until nothing significant is left, the
   top candidate does not improve the diagram, or ``max_effects`` are in.

The first effect kept is *the* effect of the report (``metrics["effect"]``); every step
is recorded. Optionally a UDE is fitted on the mechanistic model and on the refined one.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from ..analysis.diagram import _evaluate
from ..data.orbit import OrbitDataset
from ..fitting import fit, identify_mechanistic, prepare
from ..models.library import LIBRARY, STRUCTURAL, effect
from ..models.refined import describe
from ..models.ude import UDE
from ..training.identify import augment, identify
from .explain import choose_shape, explain



@dataclass
class Stage:
    """One model of the loop: the model, its diagram and its metrics."""
    name: str
    model: UDE
    diagram: dict
    metrics: dict
    identification: dict
    scales: np.ndarray


@dataclass
class LoopResult:
    system: str
    before: Stage
    after: Stage
    added: list                       # [(key, shape)] kept, in order
    steps: list = field(default_factory=list)
    explanations: list = field(default_factory=list)   # Explanation per step
    ude: dict = field(default_factory=dict)             # {"before": FitResult, "after": ...}
    ranges: dict = field(default_factory=dict)
    seconds: float = 0.0

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
        return d


def _n_parameters(model: UDE) -> int:
    import equinox as eqx
    import jax
    n = len(model.mech.fitted)
    if model.correction is not None:
        leaves = jax.tree_util.tree_leaves(eqx.filter(model.correction, eqx.is_inexact_array))
        n += int(sum(np.size(x) for x in leaves))
    return n


def _stage(name, model, ds, data, ranges, ref, ref_source, ident) -> Stage:
    scales = np.asarray(augment(data, model.mech).y_scale)
    diagram, m = _evaluate(model, ds, ranges, scales, ref, ref_source)
    m["n_parameters"] = _n_parameters(model)
    m["parameters"] = ident.get("parameters", {})
    return Stage(name, model, diagram, m, ident, scales)


def _identify(data, system, added, *, seed, bootstrap):
    mech, ident = identify(data, system, effects=tuple(added), bootstrap=bootstrap, seed=seed)
    ident["method"] = "equation error (least squares)"
    if added:
        ident["effects"] = [k for k, _ in added]
    bad = mech.unphysical()
    if bad:
        ident["unphysical"] = bad
    return mech, ident


def _better(new: dict, old: dict, min_gain: float) -> bool:
    if new["branch_rms"] is None:
        return False
    if new["missed"] < old["missed"]:
        return True
    if new["missed"] > old["missed"] or old["branch_rms"] is None:
        return False
    return new["branch_rms"] <= (1.0 - min_gain) * old["branch_rms"]


def _before(ds, data, system, ranges, ref, ref_source, seed, bootstrap) -> Stage:
    # as `ude-fit fit` does: least squares bounded to physical signs
    mech, ident = identify_mechanistic(data, system, bootstrap=bootstrap, seed=seed)
    return _stage("mechanistic", UDE(mech), ds, data, ranges, ref, ref_source, ident)


def parse_add(system: str, specs) -> list:
    """``["heave_cubic", "pitch_freeplay=0.01"]`` -> [(key, shape or None)]; ValueError
    (one line) for an unknown effect, a shape on an effect without one, or a bad number."""
    out = []
    for spec in specs:
        key, sep, val = str(spec).partition("=")
        e = effect(system, key.strip())
        shape = None
        if sep:
            if not e.shape_name:
                raise ValueError(f"--add {spec}: {e.key} has no shape parameter")
            try:
                shape = float(val)
            except ValueError:
                raise ValueError(f"--add {spec}: {val!r} is not a number") from None
            if not np.isfinite(shape) or shape <= 0:
                raise ValueError(f"--add {spec}: the {e.shape_name} must be positive")
        if any(k == e.key for k, _ in out):
            raise ValueError(f"--add {e.key} given twice")
        out.append((e.key, shape))
    return out


def refine(ds: OrbitDataset, system: str, add: list, *, reference=None, seed: int = 0,
           bootstrap: int = 200, samples: int = 32, progress=None) -> LoopResult:
    """Add the effects ``add`` ([(key, shape or None)]; a missing shape is chosen by
    cross-validation) to the mechanistic model, refit, and compare diagrams."""
    say = progress or (lambda **kw: None)
    t0 = time.perf_counter()
    data, ranges, ref, ref_source = prepare(ds, system, reference, samples)
    say(event="stage", stage="mechanistic model")
    before = _before(ds, data, system, ranges, ref, ref_source, seed, bootstrap)
    added = []
    for key, shape in add:
        if shape is None:
            shape = choose_shape(data, system, key, added=tuple(added), seed=seed)
        added.append((key, shape))
    say(event="stage", stage="refined model: " + ", ".join(k for k, _ in added))
    mech, ident = _identify(data, system, added, seed=seed, bootstrap=bootstrap)
    after = _stage("refined", UDE(mech), ds, data, ranges, ref, ref_source, ident)
    ex = explain(data, system, seed=seed, bootstrap=bootstrap)
    return LoopResult(system, before, after, added, steps=[
        {"step": 1, "candidate": ", ".join(k for k, _ in added), "kept": True,
         "reason": "given with --add", "metrics": _brief(after.metrics)}],
        explanations=[ex], ranges=ranges, seconds=time.perf_counter() - t0)


def _brief(m: dict) -> dict:
    return {k: m.get(k) for k in ("branch_rms", "branch_max", "missed", "trajectory_rms",
                                  "n_parameters")}


def close_loop(ds: OrbitDataset, system: str, *, max_effects: int = 3,
               min_gain: float = 0.1, reference=None, seed: int = 0, bootstrap: int = 200,
               samples: int = 32, progress=None) -> LoopResult:
    """explain -> add the top-ranked effect -> refit, while it improves the diagram."""
    say = progress or (lambda **kw: None)
    t0 = time.perf_counter()
    data, ranges, ref, ref_source = prepare(ds, system, reference, samples)
    say(event="stage", stage="mechanistic model")
    before = _before(ds, data, system, ranges, ref, ref_source, seed, bootstrap)
    current, added, steps, explanations = before, [], [], []
    for step in range(1, max_effects + 1):
        say(event="stage", stage=f"explaining the residual (step {step})")
        ex = explain(data, system, added=tuple(added), seed=seed, bootstrap=bootstrap)
        explanations.append(ex)
        top, why_tried = ex.top(), None
        if top is None or not ex.significant:
            # nothing beats the noise: a linear term may still be worth a try on the
            # diagram (kept only if it improves it); a structural effect never is
            top = ex.best_linear_term()
            if top is None:
                steps.append({"step": step, "candidate": None, "kept": False,
                              "reason": ex.summary})
                break
            why_tried = "not significant by cross-validation; a linear term tried on the diagram"
        trial = added + [(top["key"], top["shape"])]
        say(event="stage", stage=f"refitting with {top['name']}")
        mech, ident = _identify(data, system, trial, seed=seed, bootstrap=bootstrap)
        stage = _stage("refined", UDE(mech), ds, data, ranges, ref, ref_source, ident)
        keep = _better(stage.metrics, current.metrics, min_gain)
        reason = ("improves the diagram" if keep else
                  f"does not improve the diagram by {min_gain:.0%}")
        if why_tried:
            reason = f"{why_tried}; {reason}"
        if "unphysical" in ident:
            reason += f"; least-squares estimate unphysical ({ident['unphysical']})"
        steps.append({"step": step, "candidate": top["key"], "name": top["name"],
                      "kind": top["kind"], "shape": top["shape"], "kept": keep,
                      "significant": why_tried is None, "reason": reason,
                      "metrics": _brief(stage.metrics)})
        say(event="step", record=steps[-1])
        if not keep:
            break
        added, current = trial, stage
    # nothing kept: "after" is the mechanistic model itself
    return LoopResult(system, before, current, added, steps=steps,
                      explanations=explanations, ranges=ranges,
                      seconds=time.perf_counter() - t0)


def fit_udes(result: LoopResult, ds: OrbitDataset, opts, *, reference=None, progress=None):
    """A UDE on the mechanistic model and one on the refined model (same options)."""
    for which, stage in (("before", result.before), ("after", result.after)):
        if which == "after" and not result.added:
            result.ude["after"] = result.ude.get("before")
            continue
        result.ude[which] = fit(ds, opts, reference=reference, progress=progress,
                                mechanistic=stage.model)
    return result


def catalogue_keys(system: str) -> tuple:
    """Library keys of the effects that are structural nonlinearities (not linear or
    parameter-dependent linear terms)."""
    return tuple(e.key for e in LIBRARY[system] if e.kind == STRUCTURAL)


def metrics_document(result: LoopResult) -> dict:
    """The JSON-able summary: before, after, effect, steps, candidates."""
    def side(stage: Stage, ude_fit=None) -> dict:
        m = {k: v for k, v in stage.metrics.items() if k != "points"}
        m["points"] = stage.metrics.get("points")
        m["effects"] = describe(stage.model.mech)
        m["identification"] = {k: v for k, v in stage.identification.items()
                               if k not in ("parameters",)}
        if ude_fit is not None:
            u = ude_fit.metrics.get("ude")
            m["ude"] = None if u is None else {
                **{k: u.get(k) for k in ("branch_rms", "branch_rms_with_missed",
                                         "branch_max", "missed", "trajectory_rms", "hopf",
                                         "fold")},
                "n_parameters": _n_parameters(ude_fit.ude) if ude_fit.ude else None,
                "adequate_starts": ude_fit.metrics["starts"]["adequate"],
                "starts": ude_fit.metrics["starts"]["requested"]}
        return m

    first = result.explanations[0] if result.explanations else None
    return {
        "system": result.system,
        "before": side(result.before, result.ude.get("before")),
        "after": side(result.after, result.ude.get("after")),
        "effect": result.effect,
        "added": [{"key": k, "shape": s} for k, s in result.added],
        "steps": result.steps,
        "explanation": first.to_dict() if first else None,
        "explanations": [e.to_dict() for e in result.explanations[1:]],
        "ranges": result.ranges,
        "seconds": result.seconds,
    }
