"""How firmly each start of a fit holds the measured stability labels: prints one JSON object.

The periodic training asks every labelled orbit's stability indicator
(``stability_indicator`` of its monodromy matrix: > 0 stable, < 0 unstable) to be beyond
``TrainConfig.stability_margin`` on the labelled side, through a hinge that is zero from
there on. An orbit whose indicator sits at the margin is held there by the hinge against
the rest of the fit: the model would have it of the other stability, so a fold of its
branch lies next to it. The twenty-ninth and thirty-third sessions' failing starts on
lee2020/model2 hold the unstable orbits at 24.1 and 25.0 m/s exactly there
(docs/experiments.md).

Each point also has the period-doubling and torus tests (``secondary_indicators``: > 0
while no multiplier has passed -1 and no complex pair has crossed the unit circle), which
the training holds at the margin for an orbit labelled stable since the thirty-eighth
session (the aerofoil's fits; null where a test does not apply: an unstable orbit's torus
test, or the oscillator, whose fits do not hold them); a start trained before it can call
an orbit stable that its diagram, judging by the largest multiplier, does not.

The fit does not keep each orbit's unknowns (initial state, period), so they are solved
again here: the training's own objective over the unknowns alone, the start's model fixed,
from the measured orbits (Adam, then L-BFGS, as the training runs).

    python3 benchmarks/label_margins.py FIT_DIR [--data DIR] [--steps 200]

FIT_DIR is an ``ude-fit fit --out`` folder of an aerofoil fit; its ``starts/start_K.eqx``
are read (every start's model). --data defaults to the data the fit records. A fit with
``--backbone-margins`` is re-solved at the margins its metrics.json records for each orbit,
and ``in_margins`` is in units of each orbit's own margin.
"""

from __future__ import annotations

import argparse
import dataclasses
import glob
import json
import os
import re
import sys

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

from ude_fit.data.load import load  # noqa: E402
from ude_fit.model_file import load_model  # noqa: E402
from ude_fit.training.identify import augment, training_data  # noqa: E402
from ude_fit.training.losses import orbit_terms, orbit_unknowns, periodic_objective  # noqa: E402
from ude_fit.training.optimise import minimize  # noqa: E402
from ude_fit.training.options import TrainConfig  # noqa: E402


def _starts(fit_dir: str) -> list[tuple[int, str]]:
    found = []
    for path in glob.glob(os.path.join(fit_dir, "starts", "start_*.eqx")):
        m = re.fullmatch(r"start_(\d+)\.eqx", os.path.basename(path))
        if m:
            found.append((int(m.group(1)), path))
    return sorted(found)


def label_margins(model, ds, steps: int, margin: float | None = None,
                  orbit_margins=None) -> dict:
    """Every labelled orbit's indicator, closure and misfit once its unknowns are solved
    against ``model`` with the training's objective (at ``margin``, the fit's own where it
    records one, else the default; at ``orbit_margins``, one per orbit with None for the
    constant one, where the fit took them from the backbone)."""
    cfg = TrainConfig(**({} if margin is None else {"stability_margin": margin})
                      ).for_system(model.system)
    data = augment(training_data(ds), model.mech)
    own = np.full(len(ds.orbits), cfg.stability_margin)
    if orbit_margins is not None:
        used = np.array([np.nan if m is None else m for m in orbit_margins], dtype=float)
        data = dataclasses.replace(data, margin=jax.numpy.asarray(used))
        own = np.where(np.isnan(used), cfg.stability_margin, used)
    unknowns = orbit_unknowns(data, model.mech.autonomous)
    solved, loss = minimize(lambda p: periodic_objective(model, p, data, cfg), unknowns, (),
                            adam_steps=steps, lbfgs_steps=steps, lr=cfg.learning_rate)
    t = orbit_terms(model, solved, data, cfg)
    label = np.asarray(data.label)
    ind = np.asarray(t.indicator)
    # how far beyond its own margin on its labelled side: 1 at the hinge, < 1 inside it
    held = np.where(label == 0, np.nan, label * ind / own)
    return {"objective": loss, "margin": cfg.stability_margin,
            "points": [{"parameter": float(o.parameter), "amplitude_mm": 1e3 * o.amplitude,
                        "stable": o.stable, "indicator": float(i), "margin": float(m),
                        "in_margins": None if np.isnan(h) else float(h),
                        "period_doubling": _finite(s[0]), "torus": _finite(s[1]),
                        "closure": float(c), "misfit": float(f)}
                       for o, i, m, h, s, c, f in zip(ds.orbits, ind, own, held,
                                                      np.asarray(t.secondary),
                                                      np.asarray(t.closure),
                                                      np.asarray(t.fit))]}


def _finite(x) -> float | None:
    """``x`` as a JSON number; None where it is +inf (a test that does not apply: an
    unstable orbit's torus test, or a model whose fits do not hold the tests)."""
    return float(x) if np.isfinite(x) else None


def _orbit_margins(fit_dir: str):
    """The per-orbit margins the fit trained at (metrics.json's ``stability_margins``), or
    None where it used the constant one."""
    try:
        with open(os.path.join(fit_dir, "metrics.json")) as f:
            recorded = json.load(f).get("stability_margins")
    except (OSError, ValueError):
        return None
    if not recorded:
        return None
    # files written before the ``used`` field: the prediction, never below the floor
    floor = recorded["floor"]
    return [p["used"] if "used" in p else (None if p["margin"] is None
                                            else max(p["margin"], floor))
            for p in recorded["points"]]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("fit_dir")
    ap.add_argument("--data", help="the measurements (default: the sources the fit records)")
    ap.add_argument("--steps", type=int, default=200,
                    help="Adam steps, then as many L-BFGS steps (default 200)")
    args = ap.parse_args(argv)
    starts = _starts(args.fit_dir)
    if not starts:
        sys.exit(f"label_margins: no starts/start_K.eqx under {args.fit_dir}")
    records = []
    ds = None
    orbit_margins = _orbit_margins(args.fit_dir)
    for k, path in starts:
        model, header = load_model(path)
        if ds is None:
            paths = [args.data] if args.data else header["sources"]
            ds = load(paths, model.system)
        margin = (header.get("options") or {}).get("train", {}).get("stability_margin")
        rec = label_margins(model, ds, args.steps, margin, orbit_margins)
        records.append({"start": k, "adequate": header.get("adequate"), **rec})
    print(json.dumps({"fit_dir": os.path.abspath(args.fit_dir), "steps": args.steps,
                      "data": args.data, "starts": records}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
