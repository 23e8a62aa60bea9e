"""Noisy aerofoil data (σ = 0.02 and 0.04 of the heave amplitude, raw records Fourier-averaged
by the loader): the GP correction is fitted at both, the NN (the default) at 0.04, and how the
branch error and the apparent Hopf point move with noise is recorded in metrics.json and the
report.

Truth: the rig's own Hopf point, fold and orbits (tests/ude_fixtures.py).
"""

from __future__ import annotations

import json

import pytest

from tests.ude_fixtures import write_truth_campaign
from ude_fit import cli

import jax  # noqa: E402  (after the imports above, before any array)

jax.config.update("jax_enable_x64", True)       # ude_fit computes in float64 (see ude_fit docs)

AIRSPEEDS = (18.0, 19.5, 21.0, 22.5, 23.6)
SIGMAS = (0.02, 0.04)
# the network (the default, and most of the module's time) at the larger noise only; the
# GP at both
FITS = {0.02: ("gp",), 0.04: ("nn", "gp")}
# three fits, 5 min beside the other CI worker (CI order and time limit: tests/conftest.py)
pytestmark = pytest.mark.minutes(5)


@pytest.fixture(scope="module")
def noisy_fits(tmp_path_factory, flutter_truth):
    d = tmp_path_factory.mktemp("ude_noise")
    out = {}
    for sigma in SIGMAS:
        data = d / f"flutter_s{sigma}.h5"
        write_truth_campaign(data, "flutter", airspeeds=AIRSPEEDS, sigma=sigma, seed=3)
        for approx in FITS[sigma]:
            o = d / f"{approx}_{sigma}"
            rc = cli.main(["fit", str(data), "--system", "flutter", "--approximator", approx,
                           "--starts", "1",
                           "--reference-hopf", repr(flutter_truth["hopf"]),
                           "--reference-fold", repr(flutter_truth["fold"]),
                           "--out", str(o), "--quiet"])
            with open(o / "metrics.json") as fh:
                out[(approx, sigma)] = {"rc": rc, "metrics": json.load(fh),
                                        "report": (o / "report.md").read_text()}
    return out


@pytest.mark.parametrize(("sigma", "approx"), [(s, a) for s in SIGMAS for a in FITS[s]])
def test_both_approximators_fit_noisy_data(noisy_fits, approx, sigma):
    r = noisy_fits[(approx, sigma)]
    assert r["rc"] == 0
    m = r["metrics"]
    assert m["approximator"] == approx
    # the noise is averaged out over many periods: the fitted branches stay near the
    # measured points (at most one of the 10 without an orbit of its stability) ...
    assert m["ude"]["missed"] <= 1
    assert m["ude"]["branch_rms"] < m["mechanistic"]["branch_rms"]
    assert m["ude"]["branch_rms"] <= 0.03
    if approx == "nn":
        # issue 17: the default command's starts adequate on noisy simulated campaigns
        # (measured: 0.13 % at sigma = 0.02, 1.51 % at 0.04, both meeting the constraints;
        # 0.35 % at 0.04 on 2026-11-29)
        assert m["starts"]["adequate"] == m["starts"]["requested"] == 1
        assert m["ude"]["adequate"]
    # ... but the Hopf point lies beyond the last measured airspeed (23.6 m/s): it is an
    # extrapolation, and noise moves it (measured: up to several m/s at sigma = 0.04).
    # It is reported with its error against the flutter_truth, not bounded here.
    assert m["ude"]["hopf"]["reference"] is not None and m["ude"]["hopf"]["error"] is not None
    assert "| Hopf airspeed (m/s) |" in r["report"]


def test_noise_record_says_how_error_and_hopf_move(noisy_fits, capsys):
    rows = []
    for sigma in SIGMAS:
        for approx in FITS[sigma]:
            u = noisy_fits[(approx, sigma)]["metrics"]["ude"]
            rows.append((sigma, approx, u["branch_rms"], u["hopf"]["model"],
                         u["hopf"]["error"]))
    with capsys.disabled():
        print("\nsigma approximator branch_rms hopf hopf_error")
        for r in rows:
            print(f"{r[0]:.2f} {r[1]} {r[2]:.4f} {r[3]:.3f} {r[4]:+.3f}")
    # the data itself gets noisier: the measured points' own noise estimate grows with sigma
    n02 = noisy_fits[("gp", 0.02)]["metrics"]["data"]
    n04 = noisy_fits[("gp", 0.04)]["metrics"]["data"]
    assert n04["noise_rms"] > 1.5 * n02["noise_rms"]
