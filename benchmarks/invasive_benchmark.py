"""The control as a known input on a campaign held deliberately invasively (issue 17):
prints one JSON object.

For every looseness (the target's amplitude off the truth orbit's by that fraction,
alternately above and below; tests/invasive_cases.py) and noise level: the default fit of
the non-invasive campaign ("held"), of the invasive one with the recorded control as an
input ("loose+control") and without ("loose"), each judged against the rig's own open-loop
orbits: branch RMS, missed orbits, Hopf and fold airspeeds (truth 23.95 and 16.82 m/s) of
the kept UDE and of the mechanistic model, adequate starts and the wall time of the fit.
Every run also says how each campaign was held ("holding", ude_fit/data/holding.py): its
points called invasive, and the control's first harmonic (N) at the median and the largest;
with noise the "non-invasive" campaign's control is not zero either (docs/experiments.md,
fifty-third session).
``--both-sides`` also writes the invasive campaign with every target on the other side of
its orbit and fits the two together (each airspeed and branch held twice), with the control
as an input ("both+control") and without ("both"): one held orbit per airspeed and branch
cannot tell the open-loop orbit from how far the control moved it, two either side can
(docs/experiments.md, sixty-fourth session).
``--cbc`` runs the two campaigns with the CBC controller itself (``cbc-campaign run``, the
flutter plan on the embedded rig in lockstep, at 17-23 m/s, from just above the fold to
just below the Hopf point, where it holds both branches):
the non-invasive one at the plan's default tolerances, the invasive one with each
``--loose`` as the plan's ``tolerance_rel`` (under noise the regression root's
``root_se_rel``). Its points are off their orbits by what the root search left, not by a
set fraction (tests/invasive_cases.write_cbc_cases).
``--add`` adds library effects to every fit's mechanistic model (as ``ude-fit fit --add``).
``--rig-physics`` and ``--rig-effect`` start the rig in another configuration and with
undeclared physics (as ``rig-sim serve --physics``/``--effect``); its truth (the Hopf and
fold airspeeds too) is then that rig's. With ``--rig-physics c1=0 c3=0`` the aerofoil's
aerodynamic lag state no longer acts, so the quasi-steady mechanistic model is the rig's
own and a planted ``--rig-effect`` is missing physics without memory (docs/experiments.md,
thirty-ninth session). ``--loop`` runs the discovery loop (``ude-fit loop``, the
pipeline's second part) instead of the fit, and judges its refined model the same way,
with the issue's criterion against the loop on the non-invasive campaign ("criterion");
``--loop --ude`` also fits the default UDE (``--starts`` starts) on each loop's refined
model, as ``ude-fit loop --ude`` does, and judges its kept UDE the same way
("criterion_ude").

    python3 benchmarks/invasive_benchmark.py [--loose 0.05,0.15] [--sigmas 0,0.02]
        [--seeds 0] [--starts 2] [--add EFFECT ...] [--rig-physics NAME=VALUE ...]
        [--rig-effect NAME=VALUE ...] [--loop [--ude] | --both-sides | --cbc]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

import jax  # noqa: E402
import numpy as np  # noqa: E402

jax.config.update("jax_enable_x64", True)

from rig_sim.physics.configuration import configured_params  # noqa: E402
from rig_sim.physics.effects import parse_effects as rig_effect_vector  # noqa: E402
from tests.invasive_cases import (BOTH_SIDES_FITS, FITS, against_truth,  # noqa: E402
                                  criterion, fit_cases, loop_cases, truth_reference, write_cases)
from ude_fit.models.library import parse_effects  # noqa: E402


def _floats(text: str) -> list[float]:
    return [float(x) for x in text.split(",") if x.strip()]


def _against_truth(metrics) -> dict:
    return _figures_vs_truth(metrics.to_json())


def _holding(folder) -> dict:
    """How each campaign under ``folder`` was held: its points, those called invasive, the
    control's first harmonic at the median and the largest, and the largest target
    mismatch (|T1 - X1| / |X1|)."""
    from ude_fit.data import load
    out = {}
    campaigns = [p for _, paths, _ in FITS + BOTH_SIDES_FITS for p in paths]
    for path in dict.fromkeys(campaigns):                       # each campaign once
        if not os.path.exists(os.path.join(folder, path)):
            continue                                           # flipped.h5 without --both-sides
        name = os.path.splitext(path)[0]
        hs = [o.holding for o in load([os.path.join(folder, path)], "flutter")
              if o.holding is not None]
        amp = [h.control_amplitude for h in hs]
        mis = [h.target_mismatch for h in hs if h.target_mismatch is not None]
        out[name] = {"points": len(hs), "invasive": sum(h.invasive for h in hs),
                     "control_unit": hs[0].control_unit if hs else None,
                     "control_median": float(np.median(amp)) if amp else None,
                     "control_max": max(amp, default=None),
                     "target_mismatch_max": max(mis, default=None)}
    return out


def _figures(result, metrics, seconds, mechanistic) -> dict:
    out = {"adequate_starts": result.adequate, "seconds": round(seconds, 1),
           "mechanistic": _against_truth(mechanistic)}
    if metrics is not None:
        out.update(_against_truth(metrics))
    control = result.identification.get("control")
    if control is not None:
        out["control"] = control
    return out


def _figures_vs_truth(j: dict) -> dict:
    """A model's figures against the truth, from its metrics' JSON."""
    return {"branch_rms_vs_truth": j["branch_rms"], "missed": j["missed"],
            "hopf": j["hopf"]["model"], "fold": j["fold"]["model"]}


def _loop_figures(res, seconds, after, truth, reference) -> dict:
    judged = res.after.controlled
    out = {"added": [k for k, _ in res.added], "seconds": round(seconds, 1), **after,
           "judged_under_control": None if judged is None else
           {"branch_rms": judged.branch_rms, "missed": judged.missed}}
    fitted = res.ude.get("after")
    if fitted is not None:       # --ude: the kept UDE on the refined model
        kept = fitted.ude is not None
        out["ude"] = {"adequate_starts": fitted.adequate, "seconds": round(fitted.seconds, 1),
                      "kept": kept,
                      **(_figures_vs_truth(against_truth(fitted.ude, truth, fitted.ranges,
                                                         fitted.scales, reference).to_json())
                         if kept else {})}
    return out


def _criterion(runs: dict) -> dict:
    """Issue 17's invasive criterion (tests/invasive_cases.criterion) on the figures of the
    three fits (or loops)."""
    figures = lambda r: {"hopf": r["hopf"], "fold": r["fold"],
                         "branch_rms": r["branch_rms_vs_truth"]}
    return criterion(*(figures(runs[k]) for k in ("held", "loose+control", "loose")))


def _loop_run(folder, loose, sigma, seed, rig, ude_starts) -> dict:
    truth = write_cases(folder, loose, sigma=sigma, seed=seed, rig=rig)
    reference = truth_reference(rig)
    cases = loop_cases(folder, truth, seed=seed, reference=reference, ude_starts=ude_starts)
    runs = {name: _loop_figures(res, sec, _figures_vs_truth(m), truth, reference)
            for name, (res, sec, m) in cases.items()}
    out = {**runs, "criterion": _criterion(runs)}
    if ude_starts and all(runs[k]["ude"]["kept"] for k in runs):
        out["criterion_ude"] = _criterion({k: runs[k]["ude"] for k in runs})
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--loose", type=_floats, default=[0.05, 0.15])
    ap.add_argument("--sigmas", type=_floats, default=[0.0, 0.02])
    ap.add_argument("--seeds", type=lambda s: [int(x) for x in s.split(",")], default=[0])
    ap.add_argument("--starts", type=int, default=2)
    ap.add_argument("--loop", action="store_true",
                    help="the discovery loop instead of the fit (--add unused; --starts "
                    "only with --ude)")
    ap.add_argument("--ude", action="store_true",
                    help="with --loop: also the default UDE fit (--starts starts) on each "
                    "loop's refined model, as ude-fit loop --ude, and the criterion at it")
    ap.add_argument("--both-sides", action="store_true",
                    help="also hold the invasive campaign with every target on the other "
                    "side of its orbit, and fit both campaigns together, with the control as "
                    "an input (\"both+control\") and without (\"both\")")
    ap.add_argument("--cbc", action="store_true",
                    help="the campaigns run by the CBC controller (cbc-campaign run), "
                    "--loose being the invasive one's root tolerance")
    ap.add_argument("--add", nargs="+", default=[], metavar="EFFECT[=SHAPE]",
                    help="library effects added to every fit's mechanistic model (as "
                    "ude-fit fit --add), e.g. heave_unsteady_aero pitch_unsteady_aero")
    ap.add_argument("--rig-physics", nargs="+", default=[], metavar="NAME=VALUE",
                    help="the rig's other configuration (as rig-sim serve --physics)")
    ap.add_argument("--rig-effect", nargs="+", default=[], metavar="NAME=VALUE",
                    help="undeclared physics the rig is started with (rig-sim --effect)")
    a = ap.parse_args(argv)
    if a.ude and not a.loop:
        ap.error("--ude applies with --loop only (without it every fit is a UDE fit)")
    if a.both_sides and a.loop:
        ap.error("--both-sides applies to the fit only, not with --loop")
    if a.cbc and (a.loop or a.both_sides or a.rig_physics):
        ap.error("--cbc applies to the fit only, without --both-sides or --rig-physics")
    effects = parse_effects("flutter", a.add)
    try:
        configured_params("flutter", a.rig_physics)
        rig_effect_vector("flutter", a.rig_effect)
    except ValueError as exc:
        ap.error(str(exc))
    rig = {"physics": tuple(a.rig_physics), "effects": tuple(a.rig_effect)}
    runs = []
    for loose in a.loose:
        for sigma in a.sigmas:
            for seed in a.seeds:
                with tempfile.TemporaryDirectory() as d:
                    if a.loop:
                        figures = _loop_run(d, loose, sigma, seed, rig,
                                            a.starts if a.ude else 0)
                    else:
                        cases = fit_cases(d, loose, sigma=sigma, seed=seed, starts=a.starts,
                                          effects=effects, rig=rig,
                                          both_sides=a.both_sides, cbc=a.cbc)
                        figures = {name: _figures(*c) for name, c in cases.items()}
                        if all("hopf" in figures.get(k, {}) for k, _, _ in FITS):
                            figures["criterion"] = _criterion(figures)
                    figures["holding"] = _holding(d)
                # "looseness", not "loose": that is the name of a fit among the figures
                runs.append({"looseness": loose, "sigma": sigma, "seed": seed, **figures})
                print(json.dumps(runs[-1]), file=sys.stderr, flush=True)
    print(json.dumps({"benchmark": "invasive", "stage": "loop" if a.loop else "fit",
                      "campaigns": "cbc-campaign run" if a.cbc else "held on the truth",
                      "starts": a.starts, "added": a.add,
                      "rig": {**rig, "truth": truth_reference(rig)}, "runs": runs},
                     indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
