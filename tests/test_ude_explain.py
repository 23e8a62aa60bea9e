"""The residual explainer's selection (ude_fit/_explain.py) on residuals of known make-up:
states of the aerofoil rig's true orbits, a planted effect of known coefficient plus noise.
(The whole `ude-fit explain` command on rigs started with effects comes with its issue.)"""

from __future__ import annotations

import numpy as np
import pytest

from tests.ude_fixtures import write_truth_campaign
from ude_fit import load, training_data
from ude_fit._explain import flutter_library, select


@pytest.fixture(scope="module")
def states(tmp_path_factory):
    path = tmp_path_factory.mktemp("explain") / "f.h5"
    write_truth_campaign(path, "flutter", airspeeds=(18.0, 20.0, 22.0, 23.6))
    data = training_data(load([path], "flutter"))
    ys = np.asarray(data.ys)
    n_o, n, _ = ys.shape
    S = {"h": ys[:, :, 0].ravel(), "al": ys[:, :, 1].ravel(), "hd": ys[:, :, 2].ravel(),
         "ad": ys[:, :, 3].ravel(), "V": np.repeat(np.asarray(data.drive.param), n),
         "omega": np.repeat(np.asarray(data.drive.omega), n), "n": n}
    return S, np.repeat(np.arange(n_o), n)


PLANTED = [
    ("cubic heave stiffness", 0, lambda S: S["h"] ** 3, -2.0e5, None),
    ("Coulomb friction in heave", 0, lambda S: np.tanh(S["hd"] / 1e-3), -0.5, None),
    ("quadratic heave damping", 0, lambda S: np.abs(S["hd"]) * S["hd"], -20.0, None),
    ("pitch freeplay", 1, lambda S: np.clip(S["al"], -0.01, 0.01), 60.0, 0.01),
]


@pytest.mark.parametrize("name, eq, column, coef, shape", PLANTED, ids=[p[0] for p in PLANTED])
def test_planted_effect_ranked_first_with_its_coefficient(states, name, eq, column, coef,
                                                          shape):
    S, groups = states
    rng = np.random.default_rng(1)
    y = coef * column(S)
    y = y + 0.05 * np.std(y) * rng.standard_normal(y.size)
    sel = select(flutter_library(S), S, y, groups, equation=eq, seed=0)
    assert sel.significant
    top = sel.effects[0]
    assert top["name"] == name
    assert top["coefficients"][0] == pytest.approx(coef, rel=0.05)
    assert 0 < top["uncertainty"][0] < 0.05 * abs(coef)
    assert top["share"] > 0.9
    if shape is not None:
        assert top["shape"] == pytest.approx(shape, rel=0.5)


def test_pure_noise_gives_no_significant_effect(states):
    S, groups = states
    y = np.random.default_rng(2).standard_normal(S["h"].size)
    for eq in (0, 1):
        sel = select(flutter_library(S), S, y, groups, equation=eq, seed=0)
        assert not sel.significant and sel.effects == []


def test_lag_is_the_periodic_solution_of_the_first_order_lag(states):
    from ude_fit._explain import lag
    S, groups = states
    n = S["n"]
    phi = 2 * np.pi * np.arange(n) / n
    x = np.tile(np.cos(phi) + 0.3 * np.sin(3 * phi), S["h"].size // n)
    tau = 0.05
    z = lag(S, x, tau).reshape(-1, n)
    w = S["omega"].reshape(-1, n)[:, 0]
    for j in range(z.shape[0]):
        expect = (np.real(np.exp(1j * phi) / (1 + 1j * w[j] * tau))
                  + 0.3 * np.real(-1j * np.exp(3j * phi) / (1 + 3j * w[j] * tau)))
        assert np.max(np.abs(z[j] - expect)) < 1e-12


def test_planted_lag_state_found_with_its_time_constant(states):
    from ude_fit._explain import lag
    S, groups = states
    tau = 0.5 * 2 * np.pi / float(np.median(S["omega"]))      # on the library's grid
    y = -3.0 * lag(S, S["V"] * S["hd"], tau)
    sel = select(flutter_library(S), S, y, groups, equation=0, seed=0)
    top = sel.effects[0]
    assert top["name"].startswith("aerodynamic lag state in heave")
    assert top["shape"] == pytest.approx(tau)
    assert top["coefficients"][0] == pytest.approx(-3.0, rel=1e-6)
