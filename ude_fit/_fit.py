"""The fitting pipeline: mechanistic identification, several UDE starts, the adequacy check.

``fit`` is a function of a dataset and options; it returns a :class:`FitResult` holding
both models, their traced diagrams, the metrics side by side and a record of every start.

Adequacy (the paper found single trainings often land in poor local minima): a start is
*adequate* when its diagram has an orbit at every measured point with the measured
stability (nothing missed), its branch RMS error is below the mechanistic model's, and
it is within ``adequacy_factor`` times the error of the best start that passes the
other checks, or under ``adequacy_floor``, or under the data's own scatter about smooth
branches (:func:`data_scatter`), whichever is largest. The kept start is the adequate one
with the smallest branch error; if none is adequate, the one with the fewest missed points
and then the smallest error, and the result says so.
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, field

import jax
import numpy as np

from ._continuation import Branch, trace_flutter, trace_flutter_through, trace_forced
from ._data import DataError, OrbitDataset
from ._gp import fit_gp
from ._identify import TrainingData, augment, identify, residual_forces, training_data
from ._metrics import (branch_metrics, estimate_from_data, locations, model_orbit,
                       with_reference)
from ._models import UDE, duffing7, flutter_qs
from ._train import Diverged, TrainConfig, refine_mechanistic, train_ude

APPROXIMATORS = ("nn", "gp")
TRAININGS = ("trajectory", "periodic")
MECHANISTIC = ("equation", "periodic")


@dataclass(frozen=True)
class FitOptions:
    """Everything a fit takes, checked when built: a ValueError names the option (in the
    command line's spelling) and what is wrong with it."""
    system: str
    approximator: str = "nn"
    training: str = "periodic"
    starts: int = 5
    seed: int = 0
    samples: int = 32                 # samples per period of each averaged orbit
    train: TrainConfig = TrainConfig()
    adequacy_factor: float = 2.0
    adequacy_floor: float = 0.01
    gp_restarts: int = 2
    mechanistic: str = "equation"     # "equation": least squares; "periodic": then refined
    reference_hopf: float | None = None   # known Hopf airspeed (m/s), for the error figures
    reference_fold: float | None = None   # known fold airspeed (m/s)

    def __post_init__(self):
        if self.system not in ("flutter", "oscillator"):
            raise ValueError(f"--system must be flutter or oscillator, not {self.system!r}")
        if self.approximator not in APPROXIMATORS:
            raise ValueError(f"--approximator must be nn or gp, not {self.approximator!r}")
        if self.training not in TRAININGS:
            raise ValueError(f"--training must be trajectory or periodic, not "
                             f"{self.training!r}")
        if self.mechanistic not in MECHANISTIC:
            raise ValueError(f"--mechanistic must be equation or periodic, not "
                             f"{self.mechanistic!r}")
        for name, least in (("starts", 1), ("samples", 8), ("gp_restarts", 0)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < least:
                raise ValueError(f"--{name.replace('_', '-')} must be an integer at least "
                                 f"{least}, not {v!r}")
        if not isinstance(self.train, TrainConfig):
            raise ValueError(f"train must be a TrainConfig, not {self.train!r}")
        for name in ("reference_hopf", "reference_fold"):
            v = getattr(self, name)
            if v is not None and not math.isfinite(v):
                raise ValueError(f"--{name.replace('_', '-')} must be finite, not {v!r}")
        if self.system != "flutter" and self.reference():
            raise ValueError("--reference-hopf/--reference-fold apply to --system flutter "
                             "only")
        active = [p for p in self.train.penalties if p.weight]
        aero = [p for p in active if p.aerofoil_only]
        if self.system != "flutter" and aero:
            raise ValueError("/".join(f"--{p.option}" for p in aero)
                             + " apply to --system flutter only")
        if self.approximator != "nn":
            nn_only = [f"--{p.option}" for p in active]
            if self.train.param_scale != 1.0:
                nn_only.append("--param-scale")
            if self.train.param_dependence != "input":
                nn_only.append("--param-dependence polynomial")
            if nn_only:
                raise ValueError("/".join(nn_only) + " apply to --approximator nn only")

    def reference(self) -> dict:
        """The known Hopf and fold airspeeds given, as {"hopf": V, "fold": V}."""
        return {k: v for k, v in (("hopf", self.reference_hopf),
                                  ("fold", self.reference_fold)) if v is not None}

    def to_json(self) -> dict:
        d = asdict(self)
        d["train"] = self.train.for_system(self.system).to_json()   # the values actually used
        return d


@dataclass
class FitResult:
    options: FitOptions
    mechanistic: UDE
    ude: UDE | None
    identification: dict
    diagrams: dict              # {"mechanistic": {...}, "ude": {...}}: key -> Branch
    metrics: dict               # {"mechanistic", "ude", "starts", "data", ...}
    scales: np.ndarray
    ranges: dict
    starts: list = field(default_factory=list)


# ---------------------------------------------------------------------------------------
# diagrams
# ---------------------------------------------------------------------------------------

def diagram_ranges(ds: OrbitDataset) -> dict:
    """Parameter and amplitude windows for tracing, from the data's own extent."""
    A = ds.amplitudes()
    if ds.system == "flutter":
        V = ds.parameters()
        span = max(np.ptp(V), 0.1 * V.max())
        return {"v_range": [max(0.5, V.min() - 1.5 * span), V.max() + 0.75 * span],
                "amp_max": 1.4 * float(A.max())}
    out = {}
    for f in ds.frequencies_group():
        sub = ds.at_frequency(f)
        out[f"{f:g}"] = {"freq_hz": float(f), "a_range": [0.0, 1.3 * float(sub.parameters().max())],
                         "amp_max": 1.5 * float(sub.amplitudes().max())}
    return {"frequencies": out}


def trace_diagram(model: UDE, ranges: dict, scales, ds: OrbitDataset | None = None) -> dict:
    """The model's branches: {"flutter": Branch, "flutter/1": isola, ...} or {freq_hz: Branch}.

    Aerofoil: the branch from the Hopf point; with ``ds``, also the branch through every
    measured orbit that branch does not explain (a fitted model can have isolas, which a
    continuation from the Hopf point alone would never see)."""
    if model.system == "flutter":
        out = {"flutter": trace_flutter(model, v_range=ranges["v_range"],
                                        amp_max=ranges["amp_max"], scales=scales)}
        if ds is not None:
            _add_isolas(model, out, ranges, scales, ds)
        return out
    out = {}
    for key, r in ranges["frequencies"].items():
        lo, hi = r["a_range"]
        out[r["freq_hz"]] = trace_forced(model, freq_hz=r["freq_hz"],
                                         a_range=(max(lo, 0.01 * hi), hi),
                                         amp_max=r["amp_max"], scales=scales)
    return out


def _add_isolas(model, diagram, ranges, scales, ds, max_isolas: int = 6, near: float = 0.02):
    start = ds.sample(1)
    a_max = float(ds.amplitudes().max())
    for i, o in enumerate(ds.orbits):
        if len(diagram) > max_isolas:
            break
        sol = model_orbit(model, diagram, o, scales=scales)
        if sol is not None and abs(sol["amplitude"] - o.amplitude) <= near * a_max:
            continue
        # hidden states (a refined model's lags) start at zero: Newton finds them, they
        # enter linearly
        y0 = np.concatenate([start["q"][i, 0], start["qdot"][i, 0], np.zeros(model.n_hidden)])
        def known(V, amp):
            return any(abs(a - amp) <= 5e-3 * a_max
                       for b in diagram.values() for a, _ in b.amplitudes_at(V))

        b = trace_flutter_through(model, y0, 1.0 / o.frequency, o.parameter,
                                  v_range=ranges["v_range"], amp_max=ranges["amp_max"],
                                  scales=scales, known=known)
        if b is not None and b.param.size > 1:
            diagram[f"flutter/{len(diagram)}"] = b


def _evaluate(model, ds, ranges, scales, reference, ref_source) -> tuple[dict, dict]:
    diagram = trace_diagram(model, ranges, scales, ds)
    m = branch_metrics(model, diagram, ds, scales=scales)
    m.update(with_reference(locations(diagram), reference, ref_source))
    return diagram, m


# ---------------------------------------------------------------------------------------
# the pipeline
# ---------------------------------------------------------------------------------------

def _relative_noise(ds: OrbitDataset) -> float | None:
    """Median over the orbits of the raw record's residual RMS (after the harmonic fit) in
    the first coordinate, relative to that orbit's amplitude; None without raw records."""
    r = ds.noise()[:, 0] / ds.amplitudes()
    r = r[np.isfinite(r)]
    return float(np.median(r)) if r.size else None


def _unphysical(mech) -> str:
    """Names of identified damping/stiffness values that no passive structure has."""
    names = ("c_h", "c_alpha", "k_h", "k_alpha") if mech.system == "flutter" else ()
    bad = [f"{n} = {float(getattr(mech, n)):.4g}" for n in names if float(getattr(mech, n)) <= 0]
    return ", ".join(bad)


def nominal_mechanistic(system: str):
    return flutter_qs() if system == "flutter" else duffing7()


def data_scatter(ds: OrbitDataset) -> float:
    """How far the measured points themselves lie from smooth branches: the residual
    standard deviation of a quadratic in the parameter through each stability class (of 4
    or more points; per frequency for the oscillator), over the largest amplitude. No fit
    can be asked to be closer to the data than this.

    The residuals' plain RMS would underestimate the scatter: each quadratic is fitted to
    the very points it is judged on and takes 3 of their degrees of freedom (with 4 points,
    3 of 4), so the sum of squares is divided by the points left over, as the textbook
    unbiased estimate of a regression's residual variance does."""
    A, a_max = ds.amplitudes(), float(ds.amplitudes().max())
    P = ds.parameters()
    groups = [np.ones(len(ds), bool)] if ds.system == "flutter" else [
        np.round(ds.frequencies(), 6) == f for f in ds.frequencies_group()]
    res, dof = [], 0
    for g in groups:
        for label in (True, False):
            m = g & np.array([o.stable is label for o in ds.orbits])
            if m.sum() >= 4 and np.ptp(P[m]) > 0:
                c = np.polyfit(P[m], A[m], 2)
                res.extend((A[m] - np.polyval(c, P[m])).tolist())
                dof += int(m.sum()) - 3
    return float(np.sqrt(np.sum(np.square(res)) / dof) / a_max) if dof > 0 else 0.0


def fold_count(m: dict) -> int:
    """Folds in a model's diagram (every branch, every frequency)."""
    f = m.get("folds") or []
    n = sum(len(v) for v in f.values()) if isinstance(f, dict) else len(f)
    return n + len(m.get("isola_folds") or [])


def _credible(m, mech_m, fold_required: bool = False) -> bool:
    """Every check of adequacy but the comparison with the other starts: nothing missed,
    no more folds than allowed (and one at least where the data needs one), below the
    mechanistic model's error (at every frequency)."""
    if m is None or m["branch_rms"] is None or m["missed"] > 0:
        return False
    # stable and unstable orbits of a self-excited system meet at a fold; a diagram whose
    # stable and unstable branches run side by side out of the window without one claims
    # bistability at every lower airspeed
    if fold_required and fold_count(m) == 0:
        return False
    # qualitatively the mechanistic model's diagram: at most one extra fold per branch
    # family (a network that snakes through the points is not a model of them)
    families = len(mech_m["folds"]) if isinstance(mech_m.get("folds"), dict) else 1
    if fold_count(m) > fold_count(mech_m) + families:
        return False
    mech_rms = mech_m.get("branch_rms")
    if mech_rms is not None and m["branch_rms"] >= mech_rms:
        return False
    # oscillator: better than the mechanistic model at every frequency, not just overall
    for f, v in (mech_m.get("per_frequency") or {}).items():
        mine = m["per_frequency"].get(f, {}).get("branch_rms")
        if v["branch_rms"] is not None and (mine is None or mine >= v["branch_rms"]):
            return False
    return True


def _is_adequate(m, best_rms, mech_m, opts, scatter: float = 0.0,
                 fold_required: bool = False) -> bool:
    """Credible, and within ``adequacy_factor`` of the best credible start's error (or
    under the floor, or under the data's own scatter)."""
    return _credible(m, mech_m, fold_required) and m["branch_rms"] <= max(
        opts.adequacy_factor * best_rms, opts.adequacy_floor, scatter)


def judge_starts(start_metrics: list, mech_m: dict, opts: FitOptions,
                 scatter: float = 0.0, fold_required: bool = False) -> list[bool]:
    """Adequacy of each start (None for a dropped one). The reference for "within a factor
    of the best" is the best start that is itself credible: one that snakes through every
    point (folds the data does not show) fits closer than a model of the physics should,
    and must not set the bar."""
    best_rms = min((m["branch_rms"] for m in start_metrics
                    if _credible(m, mech_m, fold_required)), default=np.inf)
    return [m is not None and _is_adequate(m, best_rms, mech_m, opts, scatter, fold_required)
            for m in start_metrics]


def needs_fold(ds: OrbitDataset) -> bool:
    """Aerofoil data with stable and unstable orbits: the branch from the Hopf point turns
    at a fold to become the stable one, so a diagram needs one."""
    return ds.system == "flutter" and any(o.stable is True for o in ds) and any(
        o.stable is False for o in ds)


def _train_start(mech_model, data: TrainingData, opts: FitOptions, k: int, key, progress):
    if opts.approximator == "nn":
        return train_ude(mech_model, data, key=key, cfg=opts.train, training=opts.training,
                         progress=progress)
    Z, R = residual_forces(mech_model, data)
    gp, info = fit_gp(Z, R, seed=opts.seed + k, restarts=opts.gp_restarts)
    if not np.all(np.isfinite(np.asarray(gp.alpha))):
        raise Diverged("GP fit produced non-finite weights")
    return UDE(mech_model.mech, gp.mean_only()), {"training": "accelerations", **{
        k_: v for k_, v in info.items() if isinstance(v, (int, float, str, bool))}}


def prepare(ds: OrbitDataset, system: str, reference: dict | None, samples: int):
    """Checks and the arrays every pipeline starts from: (training data, diagram ranges,
    Hopf/fold reference, where the reference came from)."""
    if len(ds) == 0:
        raise DataError("the dataset is empty")
    if ds.system != system:
        raise DataError(f"the data is {ds.system} data, not {system}")
    data = training_data(ds, n=samples)
    if reference:
        return data, diagram_ranges(ds), dict(reference), "given"
    return (data, diagram_ranges(ds), estimate_from_data(ds),
            "estimated from the measured points")


def identify_mechanistic(data: TrainingData, system: str, *, bootstrap: int = 0,
                         seed: int = 0):
    """The least-squares mechanistic model, or the design values where that estimate is
    unphysical (recorded in the returned info)."""
    mech, ident = identify(data, system, bootstrap=bootstrap, seed=seed)
    ident["method"] = "equation error (least squares)"
    bad = _unphysical(mech)
    if bad:
        # equation error on noisy derivatives can land on negative damping or stiffness,
        # which no passive structure has: the design values stand in (and it is recorded)
        ident["equation_estimate_rejected"] = bad
        ident["equation_parameters"] = ident["parameters"]
        mech = nominal_mechanistic(system)
        ident["method"] = "design values (the least-squares estimate was unphysical)"
        ident["parameters"] = {f: float(getattr(mech, f)) for f in mech.fitted}
    return mech, ident


def fit(ds: OrbitDataset, opts: FitOptions, *, reference: dict | None = None,
        progress=None, mechanistic: UDE | None = None) -> FitResult:
    """Identify the mechanistic model, train ``opts.starts`` UDEs, keep the best adequate one.

    ``reference``: known Hopf/fold ({"hopf": V, "fold": V}, e.g. the truth) for the error
    figures; without it they are estimated from the data and marked as such.
    ``progress(event=..., **fields)`` is called along the way. ``mechanistic``: a model
    to put the correction on instead of identifying one (e.g. a refined model; its
    hidden states, if any, start from their periodic solutions along the data).
    """
    say = progress or (lambda **kw: None)
    t_start = time.perf_counter()
    if reference is None:
        reference = opts.reference() or None
    data, ranges, ref, ref_source = prepare(ds, opts.system, reference, opts.samples)
    if mechanistic is not None:
        return _fit_on(mechanistic, ds, data, opts, ranges, ref, ref_source, say, t_start,
                       verbose=progress is not None)
    say(event="stage", stage="mechanistic identification")
    mech, ident = identify_mechanistic(data, opts.system)
    mech_model = UDE(mech)
    if opts.mechanistic == "periodic":
        say(event="stage", stage="mechanistic identification (periodic orbits)")
        start_params = ident["parameters"]
        mech_model, info = refine_mechanistic(
            mech_model, data, cfg=opts.train,
            progress=(lambda **kw: say(event="train", start=0, **kw)) if progress else None)
        ident["method"] += ", then periodic-orbit output error"
        ident["start_parameters"] = start_params
        ident["parameters"] = {f: float(getattr(mech_model.mech, f))
                               for f in mech_model.mech.fitted}
        ident["periodic_loss"] = info["loss"]
    return _fit_on(mech_model, ds, data, opts, ranges, ref, ref_source, say, t_start, ident,
                   verbose=progress is not None)


def _fit_on(mech_model, ds, data, opts, ranges, ref, ref_source, say, t_start,
            ident=None, verbose: bool = False) -> FitResult:
    if ident is None:
        from ._refined import parameters_of_refined
        ident = {"method": "given", "parameters": parameters_of_refined(mech_model.mech)
                 if hasattr(mech_model.mech, "added") else
                 {f: float(getattr(mech_model.mech, f)) for f in mech_model.mech.fitted},
                 "std_error": {}}
    data = augment(data, mech_model.mech)
    scales = np.asarray(data.y_scale)
    say(event="stage", stage="mechanistic diagram")
    mech_diag, mech_m = _evaluate(mech_model, ds, ranges, scales, ref, ref_source)
    say(event="model", which="mechanistic", metrics=mech_m)

    keys = jax.random.split(jax.random.PRNGKey(opts.seed), opts.starts)
    starts = []
    for k in range(opts.starts):
        t0 = time.perf_counter()
        say(event="start", start=k + 1, starts=opts.starts)
        rec = {"start": k + 1, "seed": opts.seed, "approximator": opts.approximator}
        try:
            model, info = _train_start(
                mech_model, data, opts, k, keys[k],
                (lambda **kw: say(event="train", start=k + 1, **kw)) if verbose else None)
            rec["train_seconds"] = time.perf_counter() - t0
            diag, m = _evaluate(model, ds, ranges, scales, ref, ref_source)
            rec.update(status="ok", loss=info.get("final_loss"), info=info, metrics=m)
            rec["_model"], rec["_diagram"] = model, diag
        except Diverged as exc:
            rec.update(status="dropped", reason=str(exc), metrics=None)
        rec["seconds"] = time.perf_counter() - t0
        say(event="start_done", start=k + 1, record=rec)
        starts.append(rec)

    scatter = data_scatter(ds)
    fold_needed = needs_fold(ds)
    ok = [s for s in starts if s["status"] == "ok" and s["metrics"]["branch_rms"] is not None]
    for s, a in zip(starts, judge_starts([s["metrics"] if s["status"] == "ok" else None
                                          for s in starts], mech_m, opts, scatter,
                                         fold_needed)):
        s["adequate"] = a
    best = None
    if ok:
        best = min(ok, key=lambda s: (not s["adequate"], s["metrics"]["missed"],
                                      s["metrics"]["branch_rms"]))
    metrics = {
        "system": opts.system,
        "approximator": opts.approximator,
        "training": opts.training if opts.approximator == "nn" else "accelerations",
        "data": {"points": len(ds), "sources": list(ds.sources),
                 "stable": int(sum(1 for o in ds if o.stable is True)),
                 "unstable": int(sum(1 for o in ds if o.stable is False)),
                 "max_amplitude": float(ds.amplitudes().max()),
                 "noise_rms": _relative_noise(ds), "scatter": scatter},
        "mechanistic": {**mech_m, "parameters": ident["parameters"],
                        "identification": {k: v for k, v in ident.items()
                                           if k not in ("parameters", "std_error")},
                        "std_error": ident["std_error"]},
        "ude": None if best is None else {**best["metrics"], "start": best["start"],
                                          "adequate": best["adequate"]},
        "starts": {"requested": opts.starts,
                   "completed": len(ok),
                   "dropped": [{"start": s["start"], "reason": s["reason"]}
                               for s in starts if s["status"] == "dropped"],
                   "adequate": int(sum(s["adequate"] for s in starts)),
                   "kept": None if best is None else best["start"],
                   "criterion": {"missed": 0, "below_mechanistic": True,
                                 "factor_of_best": opts.adequacy_factor,
                                 "floor": opts.adequacy_floor,
                                 "data_scatter": scatter,
                                 "max_extra_folds_per_family": 1,
                                 "fold_required": fold_needed},
                   "records": [_public(s) for s in starts]},
        "ranges": ranges,
        "seconds": time.perf_counter() - t_start,
    }
    return FitResult(options=opts, mechanistic=mech_model,
                     ude=None if best is None else best["_model"], identification=ident,
                     diagrams={"mechanistic": mech_diag,
                               "ude": None if best is None else best["_diagram"]},
                     metrics=metrics, scales=scales, ranges=ranges, starts=starts)


def _public(s: dict) -> dict:
    out = {k: v for k, v in s.items() if not k.startswith("_") and k != "metrics"}
    m = s.get("metrics")
    if m:
        out["metrics"] = {k: m[k] for k in ("branch_rms", "branch_max", "missed",
                                            "trajectory_rms", "hopf", "fold")}
        out["metrics"]["fold_count"] = fold_count(m)
    info = out.get("info")
    if info:
        out["info"] = {k: v for k, v in info.items() if isinstance(v, (int, float, str, bool))}
    return out


def diagram_to_dict(diagram: dict | None) -> dict | None:
    if diagram is None:
        return None
    return {str(k): b.to_dict() for k, b in diagram.items()}


def diagram_from_dict(d: dict | None) -> dict | None:
    if d is None:
        return None
    return {(k if k.startswith("flutter") else float(k)): Branch.from_dict(b)
            for k, b in d.items()}
