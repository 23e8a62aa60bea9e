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
         "ad": ys[:, :, 3].ravel(), "V": np.repeat(np.asarray(data.drive.param), n)}
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
