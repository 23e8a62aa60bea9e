"""A campaign held deliberately invasively (issue 17): the simulated rig held on its own
orbits with every target's amplitude off the truth's by a fraction, alternately above and
below (what a CBC point accepted with loose tolerances is: an orbit of the controlled
system), beside the same airspeeds held on the truth; the default fit of each, with and
without the recorded control as an input, judged against the rig's own open-loop orbits.
tests/test_ude_control_input.py and benchmarks/invasive_benchmark.py share it."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from tests.ude_fixtures import write_truth_campaign

AIRSPEEDS = (19.0, 20.0, 21.0, 22.0, 23.0, 24.0, 25.5)
TRUTH_REFERENCE = {"hopf": 23.95, "fold": 16.82}      # the rig's own (docs/physics.md)
# the three fits: (name, campaign, control as an input)
FITS = (("held", "held.h5", False), ("loose+control", "loose.h5", True),
        ("loose", "loose.h5", False))


def truth_dataset(records):
    """The rig's own open-loop orbits (write_truth_campaign's records) as a dataset."""
    from ude_fit.data.orbit import Orbit, OrbitDataset
    return OrbitDataset("flutter", tuple(
        Orbit(r["parameter"], r["frequency"], r["stable"], r["coeffs"], None,
              np.full(2, np.nan), np.nan, f"truth {k}") for k, r in enumerate(records)),
        ("truth",))


def fit_cases(folder: Path, loose: float, *, sigma: float = 0.0, seed: int = 0,
              starts: int = 1, names=tuple(name for name, _, _ in FITS)) -> dict:
    """{name: (FitResult, the kept UDE's ModelMetrics against the truth, fit seconds)} for
    the fits of :data:`FITS` called ``names`` on campaigns written under ``folder``."""
    from ude_fit.analysis.diagram import _evaluate
    from ude_fit.data import load
    from ude_fit.fitting import fit
    from ude_fit.training.options import FitOptions

    folder = Path(folder)
    truth = write_truth_campaign(folder / "held.h5", "flutter", airspeeds=AIRSPEEDS,
                                 sigma=sigma, seed=seed, record_s=2.0)
    write_truth_campaign(folder / "loose.h5", "flutter", airspeeds=AIRSPEEDS, sigma=sigma,
                         seed=seed, record_s=2.0, invasive=loose)
    truth_ds = truth_dataset(truth)
    out = {}
    for name, path, control in (f for f in FITS if f[0] in names):
        t0 = time.perf_counter()
        r = fit(load([folder / path], "flutter"),
                FitOptions("flutter", starts=starts, seed=seed, control_input=control),
                reference=TRUTH_REFERENCE)
        seconds = time.perf_counter() - t0
        m = None if r.ude is None else _evaluate(r.ude, truth_ds, r.ranges, r.scales,
                                                 TRUTH_REFERENCE, "truth")[1]
        out[name] = (r, m, seconds)
    return out
