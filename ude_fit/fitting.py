"""The fitting pipeline: mechanistic identification, several UDE starts, the adequacy check.

``fit`` is a function of a dataset and options; it returns a :class:`FitResult` holding
both models, their traced diagrams, the metrics side by side and a record of every start.

Adequacy (the paper found single trainings often land in poor local minima): a start is
*adequate* when its diagram has an orbit at every measured point with the measured
stability (nothing missed), its branch RMS error is below the mechanistic model's, and
it is within ``adequacy_factor`` times the error of the best start that passes the
other checks, or under ``adequacy_floor``, or under the data's own scatter about smooth
branches (:func:`data_scatter`), whichever is largest. With the recorded control as a known
input every error compared is that of the model's orbits under the control at the points,
where its diagram has an orbit of each point's stability (:func:`.analysis.controlled.judged`:
the points are orbits of the controlled system, the diagram is the open-loop one). The
kept start is, of the adequate starts with the fewest folds, the medoid of three or more by
their Hopf and fold locations outside the measured range, else the one with the smallest
branch error
(:mod:`.analysis.keep`); if none is adequate, the one with the fewest missed points and
then the smallest error, and the result says so.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field

import jax
import numpy as np

from ._precision import require_float64
from .analysis.backbone import BackboneFit, backbone_of
from .analysis.adequacy import error_bar, judge_starts, needs_fold
from .analysis.controlled import ControlledOrbits, controlled_orbits, judged, yardstick
from .analysis.diagram import _evaluate, diagram_ranges
from .analysis.keep import KeptStart, choose_kept
from .analysis.metrics import fold_points
from .analysis.criticality import HopfCriticality, hopf_criticality
from .analysis.margins import BackboneMargins, backbone_margins
from .analysis.metrics_type import ModelMetrics
from .data.estimates import (data_scatter, estimate_from_data, parameter_scatter,
                             unstable_amplitude_line)
from .data.one_fold import fit_one_fold
from .data.orbit import DataError, OrbitDataset
from .guide_rounds import GuideRepair, GuideRounds
from .mechanistic_stage import control_record, mechanistic_stage, with_chosen_zero
from .models.ude import UDE
from .training.gp import fit_gp
from .training.control import control_input, with_control
from .training.guides import guide_orbits, with_guides
from .training.identify import TrainingData, augment, residual_forces, training_data
from .training.optimise import Diverged
from .training.parameter_errors import parameter_errors
from .training.sensor_zero import with_sensor_zero
from .training.options import FitOptions
from .training.train import refine_mechanistic, train_ensemble, train_ude

# the figures of a start's metrics its record keeps (with its fold count): the headline
# figures, and where its folds are (the adequacy rule counts them)
_RECORD_METRICS = ("branch_rms", "branch_max", "missed", "trajectory_rms", "hopf", "fold",
                   "folds", "isolas", "isola_folds")


@dataclass
class StartRecord:
    """One random start of a fit: what it produced and how it was judged."""
    start: int
    seed: int
    approximator: str
    status: str = "ok"                  # "ok", or "dropped" (its training diverged)
    reason: str | None = None           # why it was dropped
    seconds: float = 0.0
    train_seconds: float | None = None  # its training; NN starts: its share of the ensemble's
    loss: float | None = None
    info: dict = field(default_factory=dict)
    metrics: ModelMetrics | None = None  # its diagram against the data
    adequate: bool = False
    model: UDE | None = None
    diagram: dict | None = None
    guide_rounds: GuideRepair | None = None   # where its diagram broke the rule
    criticality: HopfCriticality | None = None  # its Hopf point's (self-excited data)
    # with the control as an input: its orbits under the recorded control at the points
    controlled: ControlledOrbits | None = None

    @property
    def ok(self) -> bool:
        return self.status == "ok"

    @property
    def completed(self) -> bool:
        """It trained, and its diagram has an orbit at some measured point."""
        return self.ok and self.metrics.summary.branch_rms is not None

    @property
    def judged(self) -> ModelMetrics | None:
        """The figures its adequacy and the kept start's choice read (:func:`judged`)."""
        return None if self.metrics is None else judged(self.metrics, self.controlled)

    def to_json(self) -> dict:
        """The record as metrics.json keeps it: no model, the training info's scalars and
        lists of numbers or names, the headline metrics, every fold's parameter and the fold
        count, and where each fold is in amplitude as well (``fold_points``)."""
        out = {"start": self.start, "seed": self.seed, "approximator": self.approximator}
        if not self.ok:
            return {**out, "status": self.status, "reason": self.reason,
                    "seconds": self.seconds, "adequate": self.adequate}
        out.update(train_seconds=self.train_seconds, status=self.status, loss=self.loss,
                   info={k: v for k, v in self.info.items()
                         if isinstance(v, (int, float, str, bool)) or (
                             isinstance(v, list) and all(isinstance(x, (float, str)) for x in v))},
                   seconds=self.seconds, adequate=self.adequate,
                   metrics={**{k: v for k, v in self.metrics.to_json().items()
                               if k in _RECORD_METRICS},
                            "fold_count": self.metrics.fold_count,
                            "fold_points": fold_points(self.diagram)})
        if self.guide_rounds is not None:
            out["guide_rounds"] = self.guide_rounds.to_json()
        if self.criticality is not None:
            out["hopf_criticality"] = self.criticality.to_json()
        if self.controlled is not None:
            out["controlled"] = _controlled_record(self.metrics, self.controlled,
                                                   per_point=False)
        return out


def _controlled_record(m: ModelMetrics, controlled: ControlledOrbits, *,
                       per_point: bool = True) -> dict:
    """What metrics.json keeps of a model's orbits under the recorded control: their
    figures (per point too, with ``per_point``) and the figures it was judged by."""
    c = controlled.to_json()
    if not per_point:
        c = {k: v for k, v in c.items() if k not in ("errors", "amplitudes")}
    j = judged(m, controlled).summary
    out = {**c, "judged": {"branch_rms": j.branch_rms, "branch_max": j.branch_max,
                           "missed": j.missed}}
    if per_point and controlled.invasive:
        out["held_sides"] = controlled.held_sides(m).to_json()
    return out


@dataclass
class FitResult:
    """Both models, their diagrams and metrics, every start and the one kept (None when no
    start completed). :meth:`to_json` is the document metrics.json holds."""
    options: FitOptions
    mechanistic: UDE
    ude: UDE | None
    identification: dict
    diagrams: dict              # {"mechanistic": {...}, "ude": {...}}: key -> Branch
    mechanistic_metrics: ModelMetrics
    scales: np.ndarray
    ranges: dict
    starts: list[StartRecord] = field(default_factory=list)
    kept: StartRecord | None = None
    kept_by: KeptStart | None = None    # the rule that chose it
    data: dict = field(default_factory=dict)        # what metrics.json records of the data
    fold_required: bool = False     # the data needs a fold (see adequacy.needs_fold)
    backbone: BackboneFit | None = None
    guides: dict | None = None      # the one-fold curve and guide orbits, if trained on
    margins: BackboneMargins | None = None    # the data's stability margins, if trained on
    seconds: float = 0.0
    # with the control as an input: the mechanistic model's orbits under it at the points
    mechanistic_controlled: ControlledOrbits | None = None

    @property
    def mechanistic_judged(self) -> ModelMetrics:
        """The mechanistic model's figures as the adequacy reads them (:func:`judged`)."""
        return judged(self.mechanistic_metrics, self.mechanistic_controlled)

    @property
    def adequate(self) -> int:
        """How many starts are adequate."""
        return int(sum(s.adequate for s in self.starts))

    def why_no_ude(self) -> str | None:
        """Why no UDE was kept (None when one was): every start diverged, or the trained
        ones' diagrams have no orbit at any measured point."""
        if self.ude is not None:
            return None
        if all(not s.ok for s in self.starts):
            return "every start diverged; no UDE"
        return ("no start's diagram has an orbit at any measured point (with its stability); "
                "no UDE kept")

    def to_json(self) -> dict:
        """The metrics document (metrics.json less provenance, options, figures)."""
        opts, ident, best = self.options, self.identification, self.kept
        return {
            "system": opts.system,
            "approximator": opts.approximator,
            "training": opts.training if opts.approximator == "nn" else "accelerations",
            "data": self.data,
            "mechanistic": {**self.mechanistic_metrics.to_json(),
                            **self._controlled(self.mechanistic_metrics,
                                               self.mechanistic_controlled),
                            "parameters": ident["parameters"],
                            "identification": {k: v for k, v in ident.items()
                                               if k not in ("parameters", "std_error")},
                            "std_error": ident["std_error"]},
            "ude": None if best is None else {**best.metrics.to_json(),
                                              **self._controlled(best.metrics,
                                                                 best.controlled),
                                              "start": best.start,
                                              "adequate": best.adequate},
            "starts": {"requested": opts.starts,
                       "completed": sum(s.completed for s in self.starts),
                       "dropped": [{"start": s.start, "reason": s.reason}
                                   for s in self.starts if not s.ok],
                       "adequate": self.adequate,
                       "trained_together": opts.approximator == "nn" and opts.starts_together,
                       "train_seconds": float(sum(s.train_seconds or 0.0 for s in self.starts)),
                       "kept": None if best is None else best.start,
                       "kept_by": None if self.kept_by is None else self.kept_by.to_json(),
                       "criterion": {"missed": 0, "below_mechanistic": True,
                                     "judged_by": yardstick(
                                         self.mechanistic_controlled is not None),
                                     # the bar where the mechanistic model misses every point
                                     "below_backbone": error_bar(
                                         self.mechanistic_judged,
                                         _baseline_rms(self.backbone))[1] == "backbone",
                                     "factor_of_best": opts.adequacy_factor,
                                     "floor": opts.adequacy_floor,
                                     "data_scatter": self.data["scatter"],
                                     "max_extra_folds_per_family": 1,
                                     "fold_required": self.fold_required},
                       "records": [s.to_json() for s in self.starts]},
            "backbone": None if self.backbone is None else self.backbone.to_json(),
            "guides": self.guides,
            "stability_margins": None if self.margins is None else self.margins.to_json(),
            "ranges": self.ranges,
            "seconds": self.seconds,
        }

    @staticmethod
    def _controlled(m: ModelMetrics, controlled: ControlledOrbits | None) -> dict:
        return {} if controlled is None else {"controlled": _controlled_record(m, controlled)}


# ---------------------------------------------------------------------------------------
# the pipeline
# ---------------------------------------------------------------------------------------

def _relative_noise(ds: OrbitDataset) -> float | None:
    """Median over the orbits of the raw record's residual RMS (after the harmonic fit) in
    the first coordinate, relative to that orbit's amplitude; None without raw records."""
    r = ds.noise()[:, 0] / ds.amplitudes()
    r = r[np.isfinite(r)]
    return float(np.median(r)) if r.size else None


def backbone_metrics(ds: OrbitDataset) -> BackboneFit | None:
    """The Hopf normal-form backbone fitted to the points (a third model of the data, beside
    the mechanistic model and the UDE), with its branch errors; None where it does not
    apply (forced data) or the points are too few."""
    bb = backbone_of(ds)
    if bb is None:
        return None
    return BackboneFit(bb, bb.metrics(ds.parameters(), ds.amplitudes(),
                                      [o.stable for o in ds.orbits]))


def _baseline_rms(backbone: BackboneFit | None) -> float | None:
    """The backbone's branch error, where it has an orbit at every point: the bar a start
    must pass when the mechanistic model sets none."""
    if backbone is None or backbone.errors.summary.missed:
        return None
    return backbone.errors.summary.branch_rms


def _train_starts(mech_model, data: TrainingData, opts: FitOptions, keys, say,
                  verbose: bool):
    """Every start's training: per start (UDE, info) or the Diverged that dropped it, and
    per start its training seconds (with ``starts_together`` the NN starts train as one
    vectorised ensemble, and each is charged an equal share of the ensemble's time)."""
    if opts.approximator == "nn" and not opts.starts_together:
        trained, seconds = [], []
        for k in range(opts.starts):
            t0 = time.perf_counter()
            progress = ((lambda **kw: say(event="train", start=k + 1, **kw)) if verbose
                        else None)
            try:
                trained.append(train_ude(mech_model, data, key=keys[k], cfg=opts.train,
                                         training=opts.training, progress=progress))
            except Diverged as exc:
                trained.append(exc)
            seconds.append(time.perf_counter() - t0)
        return trained, seconds
    if opts.approximator == "nn":
        say(event="stage", stage=f"training {opts.starts} starts together")
        t0 = time.perf_counter()
        trained = train_ensemble(
            mech_model, data, keys=keys, cfg=opts.train, training=opts.training,
            progress=(lambda **kw: say(event="train", start=None, **kw)) if verbose else None)
        return trained, [(time.perf_counter() - t0) / opts.starts] * opts.starts
    trained, seconds = [], []
    for k in range(opts.starts):
        t0 = time.perf_counter()
        Z, R = residual_forces(mech_model, data)
        gp, info = fit_gp(Z, R, seed=opts.seed + k, restarts=opts.gp_restarts)
        if np.all(np.isfinite(np.asarray(gp.alpha))):
            scalars = {name: v for name, v in info.items()
                       if isinstance(v, (int, float, str, bool))}
            trained.append((UDE(mech_model.mech, gp.mean_only()),
                            {"training": "accelerations", **scalars}))
        else:
            trained.append(Diverged("GP fit produced non-finite weights"))
        seconds.append(time.perf_counter() - t0)
    return trained, seconds


def prepare(ds: OrbitDataset, system: str, reference: dict | None, samples: int):
    """Checks and the arrays every pipeline starts from: (the dataset, training data,
    diagram ranges, Hopf/fold reference, where the reference came from). A dataset whose
    sensors' zero nobody chose (:func:`with_chosen_zero`) keeps each point's own mean, and
    its record says so."""
    if len(ds) == 0:
        raise DataError("the dataset is empty")
    if ds.system != system:
        raise DataError(f"the data is {ds.system} data, not {system}")
    ds = with_sensor_zero(ds)
    data = training_data(ds, n=samples)
    if reference:
        return ds, data, diagram_ranges(ds), dict(reference), "given"
    return (ds, data, diagram_ranges(ds), estimate_from_data(ds),
            "estimated from the measured points")


def fit(ds: OrbitDataset, opts: FitOptions, *, reference: dict | None = None,
        progress=None, mechanistic: UDE | None = None) -> FitResult:
    """Identify the mechanistic model, train ``opts.starts`` UDEs, keep an adequate one.

    ``reference``: known Hopf/fold ({"hopf": V, "fold": V}, e.g. the truth) for the error
    figures; without it they are estimated from the data and marked as such.
    ``progress(event=..., **fields)`` is called along the way. ``mechanistic``: a model
    to put the correction on instead of identifying one (e.g. a refined model; its
    hidden states, if any, start from their periodic solutions along the data); with
    the control as an input its gain must then be known (given, or the record in N):
    nothing is identified.
    """
    require_float64("fit")
    say = progress or (lambda **kw: None)
    t_start = time.perf_counter()
    if reference is None:
        reference = opts.reference() or None
    ds = with_chosen_zero(ds, opts)
    ds, data, ranges, ref, ref_source = prepare(ds, opts.system, reference, opts.samples)
    if mechanistic is not None:
        ident = None
        choice = opts.control()
        if choice is not None:
            ctrl = control_input(ds, choice.gain)
            if ctrl.gain is None:
                raise DataError(f"the control is recorded in {ctrl.unit}: a fit on a given "
                                "mechanistic model needs its gain (--control-gain)")
            data = with_control(data, ds, ctrl.gain)
            ident = {"method": "given", "parameters": mechanistic.mech.parameters(),
                     "std_error": {}, "control": control_record(ds, ctrl, mechanistic.mech)}
        return _fit_on(mechanistic, ds, data, opts, ranges, ref, ref_source, say, t_start,
                       ident, verbose=progress is not None)
    say(event="stage", stage="mechanistic identification")
    data, mech, ident = mechanistic_stage(ds, data, opts)
    data = augment(data, mech)      # an added effect's hidden states, along the orbits
    mech_model = UDE(mech)
    if opts.mechanistic == "periodic":
        say(event="stage", stage="mechanistic identification (periodic orbits)")
        start_params = ident["parameters"]
        mech_model, info = refine_mechanistic(
            mech_model, data, cfg=opts.train,
            progress=(lambda **kw: say(event="train", start=0, **kw)) if progress else None)
        ident["method"] += ", then periodic-orbit output error"
        ident["start_parameters"] = start_params
        ident["parameters"] = mech_model.mech.parameters()
        ident["periodic_loss"] = info["loss"]
    return _fit_on(mech_model, ds, data, opts, ranges, ref, ref_source, say, t_start, ident,
                   verbose=progress is not None)


def _fit_on(mech_model, ds, data, opts, ranges, ref, ref_source, say, t_start,
            ident=None, verbose: bool = False) -> FitResult:
    if ident is None:
        ident = {"method": "given", "parameters": mech_model.mech.parameters(),
                 "std_error": {}}
    data = augment(data, mech_model.mech)
    # with the control as an input (the data carry it), a model is judged by its orbits
    # under the control at the measured points: on these data, before any guide orbit
    measured = data
    controlled = ((lambda model: controlled_orbits(model, measured, ds))
                  if opts.control() is not None else (lambda model: None))
    margins = None
    if opts.train.backbone_margins:
        margins = backbone_margins(ds, mech_model, opts.train.stability_margin)
        if margins is not None:
            data = dataclasses.replace(data, margin=jax.numpy.asarray(margins.values))
    if opts.train.parameter_errors:
        data = dataclasses.replace(data, param_errors=parameter_errors(data, ds))
    scales = np.asarray(data.y_scale)
    guides = None
    if opts.guide_orbits:
        data, guides = _guided(ds, data, mech_model.mech, opts)
    say(event="stage", stage="mechanistic diagram")
    mech_diag, mech_m = _evaluate(mech_model, ds, ranges, scales, ref, ref_source)
    mech_c = controlled(mech_model)
    say(event="model", which="mechanistic", metrics=mech_m)

    keys = jax.random.split(jax.random.PRNGKey(opts.seed), opts.starts)
    trained, train_seconds = _train_starts(mech_model, data, opts, keys, say, verbose)
    evaluate = lambda model: _evaluate(model, ds, ranges, scales, ref, ref_source)
    repairs = GuideRounds(ds, data, mech_m, opts, evaluate, say, verbose)
    starts = []
    for k, result in enumerate(trained):
        t0 = time.perf_counter()
        say(event="start", start=k + 1, starts=opts.starts)
        rec = StartRecord(k + 1, opts.seed, opts.approximator)
        rec.train_seconds = train_seconds[k]
        if isinstance(result, Diverged):
            rec.status, rec.reason = "dropped", str(result)
        else:
            model, info = result
            diag, m = evaluate(model)
            if repairs.needed(m):
                say(event="stage", stage=f"guide rounds, start {k + 1}")
                model, diag, m, rec.guide_rounds = repairs.run(k + 1, model, diag, m, info)
                if rec.guide_rounds.kept:        # the record describes the model kept
                    info = {**info, "constraints_met": not rec.guide_rounds.kept_broken}
            rec.loss, rec.info, rec.metrics = info.get("final_loss"), info, m
            rec.model, rec.diagram = model, diag
            if ds.kind.autonomous:
                rec.criticality = hopf_criticality(model, ranges["v_range"])
            rec.controlled = controlled(model)
        rec.seconds = train_seconds[k] + time.perf_counter() - t0
        say(event="start_done", start=k + 1, record=rec)
        starts.append(rec)

    scatter = data_scatter(ds)
    fold_needed = needs_fold(ds)
    backbone = backbone_metrics(ds)
    for s, a in zip(starts, judge_starts([s.judged for s in starts], judged(mech_m, mech_c),
                                         opts, scatter, fold_needed,
                                         _baseline_rms(backbone))):
        s.adequate = a
    kept_by = choose_kept(starts, ds.parameter_spans())
    best = next((s for s in starts if s.start == kept_by.start), None)
    data_record = {**ds.record(),
                   "stable": int(sum(1 for o in ds if o.stable is True)),
                   "unstable": int(sum(1 for o in ds if o.stable is False)),
                   "max_amplitude": float(ds.amplitudes().max()),
                   "noise_rms": _relative_noise(ds), "scatter": scatter,
                   "unstable_amplitude2_slope": _unstable_slope(ds),
                   # the airspeeds' own scatter (the --parameter-errors prior's scale)
                   "parameter_scatter": (parameter_scatter(ds) if ds.kind.autonomous
                                         else None),
                   "unknown_stability": ds.unknown_stability(),
                   "point_records": ds.point_records()}
    return FitResult(options=opts, mechanistic=mech_model,
                     ude=None if best is None else best.model, identification=ident,
                     diagrams={"mechanistic": mech_diag,
                               "ude": None if best is None else best.diagram},
                     mechanistic_metrics=mech_m, scales=scales, ranges=ranges, starts=starts,
                     kept=best, kept_by=kept_by, data=data_record,
                     fold_required=fold_needed,
                     backbone=backbone, guides=guides, margins=margins,
                     seconds=time.perf_counter() - t_start, mechanistic_controlled=mech_c)


def _guided(ds: OrbitDataset, data: TrainingData, mech, opts: FitOptions):
    """``data`` with the guide orbits of the one-fold curve through ``ds``, and the record
    metrics.json keeps of them."""
    curve = fit_one_fold(ds, ds.kind.amplitude_window)
    if curve is None:
        raise DataError("--guide-orbits needs stable and unstable points (the guides follow "
                        "a curve with its fold between them)")
    guide_ds = guide_orbits(ds, curve, opts.guide_orbits)
    record = {"curve": curve.to_json(), "weight": opts.guide_weight,
              "orbits": [{"parameter": o.parameter, "amplitude": o.amplitude,
                          "stable": o.stable} for o in guide_ds]}
    return with_guides(data, guide_ds, mech, opts.guide_weight), record


def _unstable_slope(ds: OrbitDataset) -> float | None:
    """The slope of the smaller unstable orbits' squared amplitude in the parameter (m² per
    unit; the line that points at the Hopf point), to set beside each start's Hopf
    criticality; None where the data cannot say (forced data, fewer than two unstable
    orbits)."""
    if not ds.kind.autonomous:
        return None
    un = [o for o in ds if o.stable is False]
    c = unstable_amplitude_line([o.parameter for o in un], [o.amplitude for o in un])
    return None if c is None else float(c[0])
