"""Closing the loop on rigs with planted, undeclared effects: prints one JSON object.

For each case and seed: a campaign of the rig's own true orbits held by its board at
sigma = 0.02 (tests/ude_fixtures.py) with one effect the fitter is not told about, then
`ude_fit` explain -> refine -> loop. Figures: whether the top-ranked candidate is the
planted one, the coefficient's relative error, the branch error before and after (missed
points counted at their measured amplitude), and the loop's wall time. A clean rig gives
the false-discovery count (catalogue effects reported significant).

Peer: sequentially thresholded least squares (STLSQ, the SINDy algorithm as pysindy runs
it: threshold 0.1 on unit-norm columns, 10 iterations) on the same residual and the same
candidate columns, with the mechanistic columns in. Its "top" is the candidate with the
largest normalised coefficient; its false discoveries are the catalogue effects it keeps.

    python3 benchmarks/loop_benchmark.py [--seeds N]
"""

from __future__ import annotations

import argparse
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
from ude_fit.models.library import LIBRARY, STRUCTURAL, columns, states_of  # noqa: E402
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
    args = p.parse_args()
    from ude_fit.model_file import _version
    out = {"benchmark": "loop", "version": _version(), "sigma": 0.02,
           "cases": run(args.seeds)}
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
