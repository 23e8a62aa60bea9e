"""Closing the loop on rigs with planted, undeclared effects: prints one JSON object.

Catalogue cases ("cases"): for each case and seed, a campaign of the rig's own true orbits
held by its board at sigma = 0.02 (tests/ude_fixtures.py) with one effect the fitter is not
told about, then `ude_fit` explain -> refine -> loop. Figures: whether the top-ranked
candidate is the planted one, the coefficient's relative error, the branch error before and
after (missed points counted at their measured amplitude), and the loop's wall time. A
clean rig gives the false-discovery count (catalogue effects reported significant).

Non-catalogue cases ("located"): the rig plugins of tests/located_cases.py (forms the
catalogue does not list, both rigs), the loop with the located shapes: the equation and
state located, the shape class named, the branch error before and after, the time.

Peer: sequentially thresholded least squares (STLSQ, the SINDy algorithm as pysindy runs
it: threshold 0.1 on unit-norm columns, 10 iterations) on the same residual, with the
mechanistic columns in, over the catalogue's columns (catalogue cases) or the catalogue's
and a polynomial library of the states, degrees 2 and 3 (non-catalogue cases). Its "top" is
the candidate with the largest normalised coefficient (for the non-catalogue cases: its
equation and the states it reads); its false discoveries are the catalogue effects it keeps.

With ``--ude STARTS`` each non-catalogue run also fits a UDE on the mechanistic model and
locates its learnt correction the same way (the UDE route): where it puts the effect and
whether that agrees with the residual route.

The two cases put aside at the start of that work ("aside") are run and reported apart.
Clean rigs ("clean"): both rigs without a planted effect on those campaigns; a structural
effect kept there (catalogue or located) is a false discovery.

    python3 benchmarks/loop_benchmark.py [--seeds N] [--only catalogue|located|aside|clean]
                                         [--ude S]
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import sys
import tempfile
import time

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)       # ude_fit computes in float64 (see ude_fit docs)
sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

from rig_sim.physics.flutter import FlutterParams  # noqa: E402
from tests.ude_fixtures import write_truth_campaign  # noqa: E402
from ude_fit import load, training_data  # noqa: E402
from ude_fit.discovery.loop import close_loop, metrics_document  # noqa: E402
from ude_fit.models.forms import EQUATIONS, PARAMETER, STATES  # noqa: E402
from ude_fit.models.library import (LIBRARY, STRUCTURAL, band_limited, columns,  # noqa: E402
                                    states_of)
from ude_fit.training.identify import regression  # noqa: E402

CASES = {
    "heave_cubic=5e5": (None, "heave_cubic", -5.0e5),
    "heave_friction=3": ((20.0, 21.0, 22.0, 23.0, 24.5, 25.5), "heave_friction", -3.0),
    "quadratic_damping=20": ((20.0, 21.0, 22.0, 23.0, 24.0, 25.5), "heave_quadratic_damping",
                             -20.0),
    "freeplay=0.02": (None, "pitch_freeplay", FlutterParams().k_alpha),
    "clean": (None, None, None),
}


def stlsq(X, y, threshold=0.1, iters=10):
    """Sequentially thresholded least squares on unit-norm columns (SINDy)."""
    norms = np.linalg.norm(X, axis=0)
    norms = np.where(norms > 0, norms, 1.0)
    Xn = X / norms
    keep = np.ones(X.shape[1], bool)
    c = np.zeros(X.shape[1])
    for _ in range(iters):
        c[:] = 0.0
        if not keep.any():
            break
        c[keep] = np.linalg.lstsq(Xn[:, keep], y, rcond=None)[0]
        small = np.abs(c) < threshold * np.max(np.abs(c))
        if not np.any(small & keep):
            break
        keep &= ~small
    return c, keep


def stlsq_peer(data) -> dict:
    """The peer's answer on the same residual: kept candidates per equation, ranked."""
    A, b, _, _ = regression(data, "flutter")
    S = states_of(data, "flutter")
    out = []
    for eq in range(b.shape[1]):
        base = A[:, eq, np.any(A[:, eq, :] != 0, axis=0)]
        cands, owner = [], []
        for e in LIBRARY["flutter"]:
            if e.equation != eq:
                continue
            d = sorted(e.grid(S))[len(e.grid(S)) // 2] if e.grid else None
            X = columns(e, S, d)
            cands.append(X)
            owner += [e] * X.shape[1]
        X = np.concatenate([base] + cands, 1)
        y = -b[:, eq]
        c, keep = stlsq(X, y / np.linalg.norm(y))
        nb = base.shape[1]
        for j, (e, kept) in enumerate(zip(owner, keep[nb:])):
            if kept:
                out.append((abs(c[nb + j]), e.key, e.kind))
    out.sort(reverse=True)
    seen, ranked = set(), []
    for _, key, kind in out:
        if key not in seen:
            seen.add(key)
            ranked.append((key, kind))
    return {"top": ranked[0][0] if ranked else None,
            "top_structural": next((k for k, kind in ranked if kind == STRUCTURAL), None),
            "kept": [k for k, _ in ranked]}


def polynomial_library(system: str, S: dict) -> tuple[np.ndarray, list]:
    """Monomials of degree 2 and 3 in the states (not the bifurcation parameter),
    band-limited as the catalogue's columns are; and (label, the state names it reads) of
    each."""
    keys = [k for k, (_, role) in STATES[system].items() if role != PARAMETER]
    cols, reads = [], []
    for degree in (2, 3):
        for combo in itertools.combinations_with_replacement(keys, degree):
            cols.append(np.prod([np.asarray(S[k], float) for k in combo], axis=0))
            names = [STATES[system][k][0] for k in combo]
            label = " ".join(n if names.count(n) == 1 else f"{n}^{names.count(n)}"
                             for n in dict.fromkeys(names))
            reads.append((label, sorted(set(names))))
    return band_limited(np.stack(cols, 1), int(S["n"])), reads


def stlsq_locate(data, system: str) -> dict:
    """The peer on a non-catalogue case: STLSQ over the catalogue and the polynomial
    library per equation. Its nonlinear answer is the kept structural catalogue term or
    monomial with the largest coefficient (columns and the residual of its equation at
    unit norm): its equation and the states it reads; ``top`` is the largest of any kind."""
    from ude_fit.discovery.describe import _depends_on
    A, b, _, _ = regression(data, system)
    S = states_of(data, system)
    best, top = None, None
    for eq in range(b.shape[1]):
        base = A[:, eq, np.any(A[:, eq, :] != 0, axis=0)]
        cands, owner = [], []
        for e in LIBRARY[system]:
            if e.equation != eq:
                continue
            d = sorted(e.grid(S))[len(e.grid(S)) // 2] if e.grid else None
            X = columns(e, S, d)
            cands.append(X)
            owner += [(e.key, e.kind == STRUCTURAL, _depends_on(system, e.key, d, S))] \
                * X.shape[1]
        P, poly = polynomial_library(system, S)
        owner += [(label, True, r) for label, r in poly]
        X = np.concatenate([base] + cands + [P], 1)
        y = -b[:, eq]
        c, keep = stlsq(X, y / np.linalg.norm(y))
        nb = base.shape[1]
        for j in np.flatnonzero(keep[nb:]):
            key, nonlinear, reads = owner[j]
            here = (abs(c[nb + j]), EQUATIONS[system][eq], key, reads)
            if top is None or here[0] > top[0]:
                top = here
            if nonlinear and (best is None or here[0] > best[0]):
                best = here
    out = {"top": None if top is None else top[2]}
    out.update({"equation": None, "term": None, "states": None} if best is None else
               {"equation": best[1], "term": best[2], "states": best[3]})
    return out


def _ude_route(res, ds, system: str, seed: int, starts: int) -> dict:
    """A UDE on the loop's mechanistic model; its correction located as the residual was."""
    from ude_fit.discovery.loop import compare_ude_route
    from ude_fit.fitting import FitOptions, fit
    t0 = time.perf_counter()
    f = fit(ds, FitOptions(system=system, starts=starts, seed=seed),
            mechanistic=res.before.model)
    compare_ude_route(res, f, seed=seed)
    r = res.routes
    return {"seconds": round(time.perf_counter() - t0, 2), "starts": starts,
            "kept_ude": f.ude is not None, "agree": None if r is None else r.agree,
            "ude_located": None if r is None else [r.ude.equation, r.ude.state],
            "ude_description": None if r is None else r.ude.description}


def _loop_on(path: str, write, system: str, seed: int):
    """``write(path)`` a campaign, then the loop with its defaults on it:
    (dataset, loop result, metrics document, the loop's seconds)."""
    write(path)
    ds = load([path], system)
    t0 = time.perf_counter()
    res = close_loop(ds, system, seed=seed)
    secs = time.perf_counter() - t0
    return ds, res, metrics_document(res), secs


def run_located(seeds: int, ude_starts: int = 0, aside: bool = False) -> dict:
    """The non-catalogue cases of tests/located_cases.py (with ``aside``: the two cases put
    aside) through the loop with its defaults, and the STLSQ peer on the same residual; with
    ``ude_starts`` also the UDE route (a UDE of that many starts on the mechanistic model,
    its correction located) and whether it agrees with the residual route."""
    from tests.located_cases import ASIDE, CASES, planted_states, write_case_campaign
    rows = {}
    with tempfile.TemporaryDirectory() as tmp:
        for case, (system, equation, state) in (ASIDE if aside else CASES).items():
            recs = []
            for seed in range(seeds):
                ds, res, m, secs = _loop_on(
                    os.path.join(tmp, f"{case.replace('/', '_')}_{seed}.h5"),
                    lambda p: write_case_campaign(p, case, seed=100 * seed), system, seed)
                top = next((s for q in (m["location"] or {}).get("equations", [])
                            for s in q["shapes"] if s["significant"]), None)
                top_eq = next((q["equation"] for q in m["location"]["equations"]
                               if top in q["shapes"]), None) if top else None
                eff = m["effect"] or {}
                peer = stlsq_locate(training_data(ds), system)
                recs.append({
                    "seed": seed, "located": [top_eq, top["state"] if top else None],
                    "effect": eff.get("key"), "effect_states": eff.get("states"),
                    "shape_class": eff.get("shape_class"),
                    "description": eff.get("description"),
                    "before": m["before"]["branch_rms_with_missed"],
                    "after": m["after"]["branch_rms_with_missed"],
                    "loop_seconds": round(secs, 2), "stlsq": peer})
                if ude_starts:
                    recs[-1]["ude_route"] = _ude_route(res, ds, system, seed, ude_starts)
            rows[case] = {
                "planted": [equation, state], "seeds": seeds,
                "located_right": sum(r["located"] == [equation, state] for r in recs),
                "effect_on_the_right_state": sum(
                    set(planted_states(state)) <= set(r["effect_states"] or []) for r in recs),
                "stlsq_right": sum(r["stlsq"]["equation"] == equation and
                                   sorted(r["stlsq"]["states"] or []) ==
                                   sorted(planted_states(state)) for r in recs),
                "median_error_before": float(np.median([r["before"] for r in recs])),
                "median_error_after": float(np.median([r["after"] for r in recs])),
                "median_after_over_before": float(np.median([r["after"] / r["before"]
                                                             for r in recs])),
                "median_loop_seconds": float(np.median([r["loop_seconds"] for r in recs])),
                "routes_agree": sum(bool((r.get("ude_route") or {}).get("agree"))
                                    for r in recs) if ude_starts else None,
                "ude_route_right": sum((r.get("ude_route") or {}).get("ude_located")
                                       == [equation, state] for r in recs)
                if ude_starts else None,
                "runs": recs}
            print(f"{case}: done", file=sys.stderr, flush=True)
    return rows


def run_clean(seeds: int) -> dict:
    """Both rigs without a planted effect, on the located cases' campaigns, through the loop
    with its defaults: what it keeps (the aerofoil's wake lag, the oscillator's coil lag are
    what their mechanistic models lack) and how many structural effects (catalogue or
    located) it keeps: the false discoveries of the locate route."""
    from tests.located_cases import write_clean_campaign
    rows = {}
    with tempfile.TemporaryDirectory() as tmp:
        for system in ("flutter", "oscillator"):
            recs = []
            for seed in range(seeds):
                _, _, m, secs = _loop_on(
                    os.path.join(tmp, f"clean_{system}_{seed}.h5"),
                    lambda p: write_clean_campaign(p, system, seed=100 * seed), system, seed)
                kept = [s for s in m["steps"] if s["kept"]]
                recs.append({
                    "seed": seed, "kept": [s["candidate"] for s in kept],
                    "structural_kept": [s["candidate"] for s in kept
                                        if s["kind"] in (STRUCTURAL, "located shape")],
                    "tried_and_rejected": [s["candidate"] for s in m["steps"]
                                           if not s["kept"] and s.get("candidate")],
                    "before": m["before"]["branch_rms_with_missed"],
                    "after": m["after"]["branch_rms_with_missed"],
                    "loop_seconds": round(secs, 2)})
            rows[system] = {"seeds": seeds,
                            "runs_with_a_structural_effect": sum(bool(r["structural_kept"])
                                                                 for r in recs),
                            "runs": recs}
            print(f"clean {system}: done", file=sys.stderr, flush=True)
    return rows


def run(seeds: int) -> dict:
    catalogue = {e.key for e in LIBRARY["flutter"] if e.kind == STRUCTURAL}
    rows = {}
    with tempfile.TemporaryDirectory() as tmp:
        for case, (airspeeds, key, coef) in CASES.items():
            recs = []
            for seed in range(seeds):
                path = os.path.join(tmp, f"{case}_{seed}.h5")
                write_truth_campaign(path, "flutter", airspeeds=airspeeds, sigma=0.02,
                                     seed=100 * seed, effects=() if case == "clean" else
                                     (case,), held_within=0.2)
                ds = load([path], "flutter")
                t0 = time.perf_counter()
                res = close_loop(ds, "flutter", seed=seed)
                secs = time.perf_counter() - t0
                m = metrics_document(res)
                ranked = m["explanation"]["ranked"]
                top = ranked[0]["key"] if ranked else None
                eff = m["effect"]
                peer = stlsq_peer(training_data(ds))
                rec = {"seed": seed, "top": top, "kept": [d["key"] for d in m["added"]],
                       "before": m["before"]["branch_rms_with_missed"],
                       "after": m["after"]["branch_rms_with_missed"],
                       "loop_seconds": round(secs, 2),
                       "false_discoveries": sorted(e["key"] for e in ranked
                                                   if e["key"] in catalogue
                                                   and e["key"] != key and e["significant"]),
                       "stlsq": {**peer, "false_discoveries": sorted(
                           k for k in peer["kept"] if k in catalogue and k != key)}}
                if key is not None:
                    c = eff["coefficients"][0] if eff and eff["key"] == key else None
                    rec["coefficient"] = c
                    rec["coefficient_rel_error"] = None if c is None else abs(c / coef - 1)
                recs.append(rec)
            ok = [r for r in recs if key is None or r["top"] == key]
            rows[case] = {
                "planted": key, "seeds": seeds,
                "top_is_planted": None if key is None else len(ok),
                # the loop's first kept effect (a located class may compete with it)
                "kept_is_planted": None if key is None else sum(
                    r["kept"][:1] == [key] for r in recs),
                "coefficient_within_20_percent": None if key is None else sum(
                    (r.get("coefficient_rel_error") or np.inf) <= 0.2 for r in recs),
                "stlsq_top_structural_is_planted": None if key is None else sum(
                    r["stlsq"]["top_structural"] == key for r in recs),
                "false_discoveries": sum(len(r["false_discoveries"]) for r in recs),
                "stlsq_false_discoveries": sum(len(r["stlsq"]["false_discoveries"])
                                               for r in recs),
                "median_coefficient_rel_error": None if key is None else float(np.median(
                    [r["coefficient_rel_error"] for r in recs
                     if r.get("coefficient_rel_error") is not None] or [np.nan])),
                "median_error_before": float(np.median([r["before"] for r in recs])),
                "median_error_after": float(np.median([r["after"] for r in recs])),
                "median_after_over_before": float(np.median([r["after"] / r["before"]
                                                             for r in recs])),
                "median_loop_seconds": float(np.median([r["loop_seconds"] for r in recs])),
                "runs": recs,
            }
            print(f"{case}: done", file=sys.stderr, flush=True)
    return rows


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--seeds", type=int, default=3, help="campaign seeds per case (default 3)")
    p.add_argument("--only", choices=("catalogue", "located", "aside", "clean"),
                   help="run only the catalogue cases, the non-catalogue cases, the two "
                   "non-catalogue cases put aside or both clean rigs")
    p.add_argument("--ude", type=int, default=0, metavar="STARTS",
                   help="non-catalogue cases: also the UDE route with a UDE of STARTS "
                   "starts, and whether it agrees with the residual route (default 0: not)")
    args = p.parse_args()
    from ude_fit.model_file import _version
    out = {"benchmark": "loop", "version": _version(), "sigma": 0.02}
    if args.only in (None, "catalogue"):
        out["cases"] = run(args.seeds)
    if args.only in (None, "located"):
        out["located"] = run_located(args.seeds, args.ude)
    if args.only in (None, "aside"):
        out["aside"] = run_located(args.seeds, args.ude, aside=True)
    if args.only in (None, "clean"):
        out["clean"] = run_clean(args.seeds)
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
