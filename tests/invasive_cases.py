"""A campaign held deliberately invasively (issue 17): the simulated rig held on its own
orbits with every target's amplitude off the truth's by a fraction, alternately above and
below (what a CBC point accepted with loose tolerances is: an orbit of the controlled
system), beside the same airspeeds held on the truth; the default fit of each, with and
without the recorded control as an input, judged against the rig's own open-loop orbits.
tests/test_ude_control_input.py and benchmarks/invasive_benchmark.py share it."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from tests.ude_fixtures import write_truth_campaign

AIRSPEEDS = (19.0, 20.0, 21.0, 22.0, 23.0, 24.0, 25.5)
TRUTH_REFERENCE = {"hopf": 23.95, "fold": 16.82}      # the rig's own (docs/physics.md)
# the three fits: (name, campaigns, control as an input)
FITS = (("held", ("held.h5",), False), ("loose+control", ("loose.h5",), True),
        ("loose", ("loose.h5",), False))
# with both sides (write_cases): every airspeed and branch held twice, once with the
# invasive campaign's target and once with its sign flipped, fitted together
BOTH_SIDES = ("loose.h5", "flipped.h5")
BOTH_SIDES_FITS = (("both+control", BOTH_SIDES, True), ("both", BOTH_SIDES, False))


def criterion(held: dict, ctrl: dict, loose: dict) -> dict:
    """Issue 17's invasive criterion: the fit (or loop) with the control as an input
    (``ctrl``) against the same on the non-invasive campaign (``held``): Hopf and fold
    within 0.1 m/s of its, branch error against the truth at most 1.5 times its; and how
    much worse the same without the control (``loose``) is. Each a dict of "hopf" and
    "fold" (m/s or None) and "branch_rms" against the truth."""
    apart = lambda k: (None if ctrl[k] is None or held[k] is None
                       else abs(ctrl[k] - held[k]))
    out = {"hopf_apart": apart("hopf"), "fold_apart": apart("fold"),
           "error_ratio": ctrl["branch_rms"] / held["branch_rms"],
           "without_control_ratio": loose["branch_rms"] / held["branch_rms"]}
    out["met"] = bool(out["hopf_apart"] is not None and out["hopf_apart"] <= 0.1
                      and out["fold_apart"] is not None and out["fold_apart"] <= 0.1
                      and out["error_ratio"] <= 1.5)
    return out


def criterion_figures(metrics: dict) -> dict:
    """A model's metrics against the truth (``ModelMetrics.to_json``) as :func:`criterion`
    reads them."""
    return {"hopf": metrics["hopf"]["model"], "fold": metrics["fold"]["model"],
            "branch_rms": metrics["branch_rms"]}


def truth_dataset(records):
    """The rig's own open-loop orbits (write_truth_campaign's records) as a dataset."""
    from ude_fit.data.orbit import Orbit, OrbitDataset
    return OrbitDataset("flutter", tuple(
        Orbit(r["parameter"], r["frequency"], r["stable"], r["coeffs"], None,
              np.full(2, np.nan), np.nan, f"truth {k}") for k, r in enumerate(records)),
        ("truth",))


def truth_reference(rig: dict) -> dict:
    """The Hopf and fold airspeeds of the rig started with ``rig`` (write_truth_campaign's
    ``effects`` and ``physics``): the design rig's known ones, else its truth branch's."""
    if not any(rig.values()):
        return TRUTH_REFERENCE
    from tests.ude_fixtures import flutter_branch
    branch = flutter_branch(max(26.0, max(AIRSPEEDS) + 0.5), tuple(rig.get("effects", ())),
                            None, tuple(rig.get("physics", ())))
    return {"hopf": float(branch.hopf[0]), "fold": float(branch.folds[0]["V"])}


def write_cases(folder: Path, loose: float, *, sigma: float = 0.0, seed: int = 0,
                rig: dict | None = None, both_sides: bool = False):
    """Write the non-invasive campaign (held.h5) and the invasive one (loose.h5) under
    ``folder`` on the rig started with ``rig`` ({"effects": ..., "physics": ...}, as
    write_truth_campaign takes them; the design rig by default), with ``both_sides`` also
    the invasive one with every target on the other side of its orbit (flipped.h5);
    returns the truth's open-loop orbits as a dataset."""
    folder = Path(folder)
    rig = rig or {}
    truth = write_truth_campaign(folder / "held.h5", "flutter", airspeeds=AIRSPEEDS,
                                 sigma=sigma, seed=seed, record_s=2.0, **rig)
    for name, looseness in (("loose.h5", loose), ("flipped.h5", -loose))[:1 + both_sides]:
        write_truth_campaign(folder / name, "flutter", airspeeds=AIRSPEEDS, sigma=sigma,
                             seed=seed, record_s=2.0, invasive=looseness, **rig)
    return truth_dataset(truth)


# Where the CBC controller's flutter plan holds both branches, from just above the fold
# (16.82 m/s) to just below the Hopf point (23.95): the criterion compares fold points, and
# a fold measured near, not extrapolated from orbits 2.4 m/s away, is one the campaign
# pins (at 19-23 m/s the folds of the fits lay 0.05-0.20 m/s apart, experiments.md,
# sixty-sixth session). The plan holds both branches at 17 m/s with and without noise.
CBC_AIRSPEEDS = (17.0, 18.0, 19.0, 20.0, 21.0, 22.0, 23.0)


def _cbc_toml(name: str, seed: int, sigma: float, effects: tuple, root: dict) -> str:
    effects_toml = ", ".join(f'"{e}"' for e in effects)
    root_toml = "\n".join(f"{k} = {v!r}" for k, v in root.items())
    return f"""[campaign]
name = "{name}"
rig = "flutter"
seed = {seed}

[rig]
lockstep = true
noise = {sigma!r}
effects = [{effects_toml}]

[loop]
rate_hz = 200
lockstep_slice_s = 0.2

[parameter]
values = {list(CBC_AIRSPEEDS)}

[cbc]
{root_toml}
"""


def write_cbc_cases(folder: Path, tolerance: float, *, sigma: float = 0.0, seed: int = 0,
                    effects: tuple = ()):
    """Run the CBC controller's flutter plan (``cbc-campaign run``, the embedded rig in
    lockstep, ``effects`` undeclared) at :data:`CBC_AIRSPEEDS` twice: at the plan's default
    tolerances (held.h5) and with the root accepted at ``tolerance`` (loose.h5: the plan's
    ``tolerance_rel``; under noise, ``root_method = "regression"`` and its ``root_se_rel``),
    what "a campaign held with loose tolerances" is on the wire; returns the rig's own
    open-loop orbits at those airspeeds as a dataset."""
    folder = Path(folder)
    root = {"root_method": "regression", "navg": 20} if sigma > 0 else {}
    loose = {"root_se_rel": tolerance} if sigma > 0 else {"tolerance_rel": tolerance}
    repo = Path(__file__).resolve().parents[1]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        [str(repo), *filter(None, [os.environ.get("PYTHONPATH")])])}
    for name, settings in (("held", root), ("loose", {**root, **loose})):
        toml = folder / f"{name}.toml"
        toml.write_text(_cbc_toml(f"invasive-{name}", seed, sigma, tuple(effects), settings))
        run = subprocess.run([sys.executable, "-m", "cbc_controller.cli", "run", str(toml),
                              "--out", str(folder / f"{name}.h5")], env=env, cwd=repo,
                             capture_output=True, text=True)
        if run.returncode != 0:
            raise RuntimeError(f"cbc-campaign run {toml.name} failed: "
                               f"{run.stderr.strip().splitlines()[-1:]}")
    truth = write_truth_campaign(folder / "truth.h5", "flutter", airspeeds=CBC_AIRSPEEDS,
                                 effects=tuple(effects), record_s=0.0)
    return truth_dataset(truth)


def against_truth(model, truth_ds, ranges, scales, reference: dict = TRUTH_REFERENCE):
    """``model``'s ModelMetrics against the rig's open-loop orbits (``reference``: its
    Hopf and fold airspeeds)."""
    from ude_fit.analysis.diagram import _evaluate
    return _evaluate(model, truth_ds, ranges, scales, reference, "truth")[1]


def mechanistic_cases(folder: Path, loose: float, effects: tuple = (), *,
                      sigma: float = 0.0, seed: int = 0) -> tuple[dict, object]:
    """({name: (the mechanistic model's ModelMetrics against the truth, its
    identification)} for the fits of :data:`FITS`, the truth's open-loop orbits as a
    dataset): the mechanistic stage alone (equation error, seconds), with the library
    ``effects`` added ((key, shape or None) pairs, as --add), on the campaigns written
    under ``folder``."""
    from ude_fit.data import load
    from ude_fit.fitting import prepare
    from ude_fit.mechanistic_stage import mechanistic_stage
    from ude_fit.models.ude import UDE
    from ude_fit.training.identify import augment
    from ude_fit.training.options import FitOptions

    truth_ds = write_cases(folder, loose, sigma=sigma, seed=seed)
    out = {}
    for name, paths, control in FITS:
        ds = load([Path(folder) / p for p in paths], "flutter")
        opts = FitOptions("flutter", control_input=control, mechanistic_effects=effects)
        _, data, ranges, _, _ = prepare(ds, "flutter", TRUTH_REFERENCE, opts.samples)
        data, mech, ident = mechanistic_stage(ds, data, opts)
        data = augment(data, mech)
        out[name] = (against_truth(UDE(mech), truth_ds, ranges, np.asarray(data.y_scale)),
                     ident)
    return out, truth_ds


def fit_cases(folder: Path, loose: float, *, sigma: float = 0.0, seed: int = 0,
              starts: int = 1, names=tuple(name for name, _, _ in FITS),
              effects: tuple = (), rig: dict | None = None,
              both_sides: bool = False, cbc: bool = False) -> dict:
    """{name: (FitResult, the kept UDE's ModelMetrics against the truth, fit seconds, the
    mechanistic model's ModelMetrics against the truth)} for the fits of :data:`FITS`
    called ``names`` (with ``both_sides`` those of :data:`BOTH_SIDES_FITS` too) on
    campaigns written under ``folder``, with the library ``effects`` added to the
    mechanistic model (as --add), on the rig started with ``rig`` (as :func:`write_cases`
    takes it). With ``cbc`` the two campaigns are the CBC controller's
    (:func:`write_cbc_cases`, ``loose`` its tolerance; the rig's ``effects`` only)."""
    from ude_fit.data import load
    from ude_fit.fitting import fit
    from ude_fit.training.options import FitOptions

    folder = Path(folder)
    if cbc:
        truth_ds = write_cbc_cases(folder, loose, sigma=sigma, seed=seed,
                                   effects=(rig or {}).get("effects", ()))
    else:
        truth_ds = write_cases(folder, loose, sigma=sigma, seed=seed, rig=rig,
                               both_sides=both_sides)
    reference = truth_reference(rig or {})
    fits = [f for f in FITS if f[0] in names] + list(BOTH_SIDES_FITS if both_sides else ())
    out = {}
    for name, paths, control in fits:
        t0 = time.perf_counter()
        r = fit(load([folder / p for p in paths], "flutter"),
                FitOptions("flutter", starts=starts, seed=seed, control_input=control,
                           mechanistic_effects=effects),
                reference=reference)
        seconds = time.perf_counter() - t0
        m = None if r.ude is None else against_truth(r.ude, truth_ds, r.ranges, r.scales,
                                                     reference)
        out[name] = (r, m, seconds, against_truth(r.mechanistic, truth_ds, r.ranges,
                                                  r.scales, reference))
    return out


def loop_cases(folder: Path, truth_ds, *, bootstrap: int = 20, seed: int = 0,
               reference: dict = TRUTH_REFERENCE, ude_starts: int = 0) -> dict:
    """{name: (LoopResult, seconds, its refined model's metrics against the truth as JSON)}
    for the discovery loop (``ude-fit loop``, the pipeline's second part) on the campaigns
    :func:`write_cases` wrote under ``folder`` (``truth_ds``: what it returned), one loop
    per :data:`FITS` entry, with the control as an input where the entry says so. With
    ``ude_starts`` the default UDE fit on the refined model (as ``ude-fit loop --ude``, that
    many starts) goes in each result's ``ude["after"]``; its seconds are not counted."""
    from ude_fit.data import load
    from ude_fit.discovery.loop import close_loop, fit_stage_ude
    from ude_fit.training.control import ControlChoice
    from ude_fit.training.options import FitOptions

    out = {}
    for name, paths, control in FITS:
        t0 = time.perf_counter()
        ds = load([Path(folder) / p for p in paths], "flutter")
        res = close_loop(ds, "flutter", seed=seed, bootstrap=bootstrap, reference=reference,
                         control=ControlChoice("flutter") if control else None)
        seconds = time.perf_counter() - t0
        if ude_starts:
            res.ude["after"] = fit_stage_ude(
                res, res.after, ds, FitOptions("flutter", starts=ude_starts, seed=seed),
                reference=reference)
        out[name] = (res, seconds, against_truth(res.after.model, truth_ds, res.ranges,
                                                 res.after.scales, reference).to_json())
    return out
