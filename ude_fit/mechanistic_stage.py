"""A fit's mechanistic stage: the model identified from the data by equation error
(bounded to physical signs, the user's given values in place, the recorded control as a
known input where asked), where every parameter came from, and the sensors' zero the
points are taken about where their files do not record it (chosen by the model's own
diagram, :func:`with_chosen_zero`). :func:`ude_fit.fitting.fit` runs it first."""

from __future__ import annotations

import dataclasses

import numpy as np

from .analysis.diagram import _evaluate, diagram_ranges
from ._precision import require_float64
from .data.estimates import estimate_from_data
from .data.orbit import OrbitDataset
from .models.mechanistic import FLUTTER_NOMINAL
from .models.parameter_file import MechanisticParameters
from .models.ude import UDE
from .training.control import (ControlChoice, ControlInput, against_heave_stiffness,
                               control_input, with_control)
from .training.identify import INPUT_GAIN, TrainingData, augment, identify, training_data
from .training.options import FitOptions
from .training.sensor_zero import AUTO, ZeroJudgement, with_sensor_zero


def with_chosen_zero(ds: OrbitDataset, opts: FitOptions) -> OrbitDataset:
    """``ds`` about the sensors' zero ``opts.sensor_zero`` asks for, where some file did not
    record it (:mod:`~.training.sensor_zero`), with the mechanistic model's known geometry.

    ``auto`` takes the zero identified from all points where the mechanistic model
    identified with it reproduces the measured diagram better than with each point's own
    mean (fewer points missed, then a smaller branch error), and each point's own mean
    otherwise, a tie included. The zero is identified through that model's equations: a
    model that meets the points with it has shown it can place it (the held-out simulated
    configurations), one that misses them with either zero has not (lee2020/model2, where
    the identified zero lowers the equation error by 2 % and changes the quadratic pitch
    stiffness ninefold). The record keeps both diagrams' figures."""
    if opts.sensor_zero == AUTO and (not ds.zero_unknown().any()
                                     or ds.sensor_zero is not None):
        return ds                       # nothing to choose, or chosen already
    require_float64("choosing the sensors' zero")
    geometry = known_geometry(opts.mechanistic_parameters)
    if opts.sensor_zero != AUTO:
        return with_sensor_zero(ds, geometry, opts.sensor_zero)
    identified = with_sensor_zero(ds, geometry, "identified")
    if not identified.sensor_zero.identified:
        return identified           # its record says why each own mean was kept
    own = with_sensor_zero(ds, geometry, "own-means")
    judged = {"own-means": _mechanistic_diagram(own, opts),
              "identified": _mechanistic_diagram(identified, opts)}
    better = judged["identified"].rank() < judged["own-means"].rank()
    chosen = identified if better else own
    said = {k: j.describe(len(ds)) for k, j in judged.items()}
    method = (f"{chosen.sensor_zero.method}; chosen (auto) because the mechanistic model "
              f"identified with the identified zero meets the measured diagram "
              f"{'better' if better else 'no better'} ({said['identified']}) than with each "
              f"point's own mean ({said['own-means']})")
    return dataclasses.replace(chosen, sensor_zero=dataclasses.replace(
        chosen.sensor_zero, judged=judged, method=method))


def _mechanistic_diagram(ds: OrbitDataset, opts: FitOptions) -> ZeroJudgement:
    """The fit's mechanistic model identified on ``ds`` (equation error) and its diagram
    against the points: how many it misses and its branch error."""
    data = training_data(ds, n=opts.samples)
    data, mech, _ = mechanistic_stage(ds, data, opts)
    data = augment(data, mech)
    _, m = _evaluate(UDE(mech), ds, diagram_ranges(ds), np.asarray(data.y_scale),
                     estimate_from_data(ds), "estimated from the measured points")
    return ZeroJudgement(m.summary.missed, m.summary.branch_rms)


def known_geometry(given: MechanisticParameters | None) -> dict | None:
    """The mechanistic model's known geometry with the user's ``given`` values in it; None
    (the design's) where the user gave none."""
    if given is None or not given.known:           # only the aerofoil has known geometry
        return None
    return {**FLUTTER_NOMINAL, **given.known}


def identify_mechanistic(data: TrainingData, system: str, *, bootstrap: int = 0,
                         seed: int = 0, given: MechanisticParameters | None = None,
                         free_input: bool = False, effects: tuple = ()):
    """The mechanistic model from the data: damping and stiffness by least squares bounded
    to their physical signs (never another rig's values), with the user's ``given`` values
    in their place and the library ``effects`` ((key, shape) pairs, the shape None for an
    effect without one) added as terms of their own. The info's ``sources`` says where
    every parameter came from."""
    base = known_geometry(given)
    chosen = tuple(effects)
    mech, ident = identify(data, system, base, chosen,
                           fixed=None if given is None else given.fitted,
                           bootstrap=bootstrap, seed=seed, free_input=free_input)
    ident["method"] = "equation error (least squares, damping and stiffness bounded at 0)"
    if chosen:
        ident["method"] += ", with " + ", ".join(k for k, _ in chosen) + " added"
        ident["effects"] = [{"key": k, "shape": v} for k, v in chosen]
    ident["known"] = {n: v for n, v in mech.values().items() if n not in ident["parameters"]}
    ident["sources"] = parameter_sources(mech, ident, given)
    return mech, ident


def mechanistic_stage(ds: OrbitDataset, data: TrainingData, opts: FitOptions):
    """A fit's mechanistic identification by equation error: (training data, mechanistic
    model, identification info). With the control as an input the data come back carrying
    it as a known heave force (and the gain is identified where it is not known)."""
    choice = opts.control()
    if choice is not None:
        return identify_with_control(ds, data, choice, given=opts.mechanistic_parameters,
                                     effects=opts.mechanistic_effects)
    mech, ident = identify_mechanistic(data, opts.system, given=opts.mechanistic_parameters,
                                       effects=opts.mechanistic_effects)
    return data, mech, ident


def identify_with_control(ds: OrbitDataset, data: TrainingData, choice: ControlChoice, *,
                          given: MechanisticParameters | None = None, effects: tuple = (),
                          bootstrap: int = 0, seed: int = 0):
    """The training data with the recorded control as a known heave force, the mechanistic
    model (with the library ``effects``) identified on it, the gain with it where the
    ``choice`` does not know it, and the info (its ``control`` says the gain and where it
    came from, and each point's control force against the heave spring's)."""
    ctrl = control_input(ds, choice.gain)
    if ctrl.gain is None:
        raw = with_control(data, ds, 1.0)
        mech, ident = identify_mechanistic(raw, choice.system, given=given, free_input=True,
                                           effects=effects, bootstrap=bootstrap, seed=seed)
        gain = ident["parameters"].pop(INPUT_GAIN)
        se = ident["std_error"].pop(INPUT_GAIN, None)
        ident.get("bootstrap_std", {}).pop(INPUT_GAIN, None)
        ident["sources"].pop(INPUT_GAIN, None)
        ctrl = ControlInput(ctrl.unit, float(gain), ctrl.source)
        ident["control"] = {**control_record(ds, ctrl, mech), "gain_std_error": se}
    else:
        mech, ident = identify_mechanistic(with_control(data, ds, ctrl.gain), choice.system,
                                           given=given, effects=effects,
                                           bootstrap=bootstrap, seed=seed)
        ident["control"] = control_record(ds, ctrl, mech)
    return with_control(data, ds, ctrl.gain), mech, ident


def control_record(ds: OrbitDataset, ctrl: ControlInput, mech) -> dict:
    """What metrics.json keeps of a fit's control input: unit, gain and its source, and
    each point's control force against ``mech``'s heave spring."""
    return {**ctrl.to_json(), "against_heave_stiffness": against_heave_stiffness(
        ds, ctrl.gain, mech.values()["k_h"])}


def parameter_sources(mech, ident: dict, given: MechanisticParameters | None) -> dict:
    """Every parameter of ``mech`` by name: where its value came from."""
    given_names = set() if given is None else set(given.known) | set(given.fitted)
    out = {}
    for name in mech.values():
        if name in given_names:
            out[name] = f"user file {given.path}"
        elif name in ident.get("at_bound", ()):
            out[name] = (f"identified from the orbits, at its physical bound 0 (the "
                         f"unconstrained estimate was {ident['unconstrained'][name]:.4g})")
        elif name in ident["parameters"]:
            out[name] = "identified from the orbits (least squares)"
        else:
            out[name] = "known geometry (design value)"
    return out
