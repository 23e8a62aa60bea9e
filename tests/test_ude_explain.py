"""The residual explainer's selection (ude_fit/_explain.py) on residuals of known make-up:
states of the aerofoil rig's true orbits, a planted effect of known coefficient plus noise.
(The whole loop on rigs started with effects: tests/test_ude_loop.py.)"""

from __future__ import annotations

import numpy as np
import pytest

from tests.ude_fixtures import write_truth_campaign
from ude_fit import load, training_data
from ude_fit.discovery.explain import select
from ude_fit.models.library import lag, LIBRARY, sample_states

import jax  # noqa: E402  (after the imports above, before any array)

jax.config.update("jax_enable_x64", True)       # ude_fit computes in float64 (see ude_fit docs)


@pytest.fixture(scope="module")
def states(tmp_path_factory):
    path = tmp_path_factory.mktemp("explain") / "f.h5"
    write_truth_campaign(path, "flutter", airspeeds=(18.0, 20.0, 22.0, 23.6))
    data = training_data(load([path], "flutter"))
    ys = np.asarray(data.ys)
    n_o, n, _ = ys.shape
    S = sample_states("flutter", ys, np.asarray(data.drive.param),
                      np.asarray(data.drive.omega))
    return S, np.repeat(np.arange(n_o), n)


PLANTED = [
    ("heave_cubic", 0, lambda S: S["h"] ** 3, -2.0e5, None),
    ("heave_friction", 0, lambda S: np.tanh(S["hd"] / 1e-3), -0.5, None),
    ("heave_quadratic_damping", 0, lambda S: np.abs(S["hd"]) * S["hd"], -20.0, None),
    ("pitch_freeplay", 1, lambda S: np.clip(S["al"], -0.01, 0.01), 60.0, 0.01),
]


def band(S, x):
    """What a K-harmonic measurement shows of a force: its first 7 harmonics per orbit."""
    from ude_fit.models.library import band_limited
    return band_limited(np.asarray(x, float)[:, None], S["n"])[:, 0]


@pytest.mark.parametrize("name, eq, column, coef, shape", PLANTED, ids=[p[0] for p in PLANTED])
def test_planted_effect_ranked_first_with_its_coefficient(states, name, eq, column, coef,
                                                          shape):
    S, groups = states
    rng = np.random.default_rng(1)
    y = coef * band(S, column(S))
    y = y + 0.05 * np.std(y) * rng.standard_normal(y.size)
    sel = select(LIBRARY["flutter"], S, y, groups, equation=eq, seed=0)
    assert sel.significant
    top = sel.effects[0]
    assert top["key"] == name and top["significant"]
    assert top["coefficients"][0] == pytest.approx(coef, rel=0.05)
    assert 0 < top["uncertainty"][0] < 0.05 * abs(coef)
    assert top["share"] > 0.9
    if shape is not None:
        assert top["shape"] == pytest.approx(shape, rel=0.5)


def test_pure_noise_gives_no_significant_effect(states):
    S, groups = states
    y = np.random.default_rng(2).standard_normal(S["h"].size)
    for eq in (0, 1):
        sel = select(LIBRARY["flutter"], S, y, groups, equation=eq, seed=0)
        assert not sel.significant and sel.effects == []


def test_lag_is_the_periodic_solution_of_the_first_order_lag(states):
    S, groups = states
    n = S["n"]
    phi = 2 * np.pi * np.arange(n) / n
    x = np.tile(np.cos(phi) + 0.3 * np.sin(3 * phi), S["h"].size // n)
    tau = 0.05
    z = lag(S, x, tau).reshape(-1, n)
    w = S["w"].reshape(-1, n)[:, 0]
    for j in range(z.shape[0]):
        expect = (np.real(np.exp(1j * phi) / (1 + 1j * w[j] * tau))
                  + 0.3 * np.real(-1j * np.exp(3j * phi) / (1 + 3j * w[j] * tau)))
        assert np.max(np.abs(z[j] - expect)) < 1e-12


def test_planted_lag_state_found_with_its_time_constant(states):
    S, groups = states
    tau = 0.37 * 2 * np.pi / float(np.median(S["w"]))      # between the grid's points
    y = -3.0 * lag(S, S["V"] * S["hd"], tau)
    sel = select(LIBRARY["flutter"], S, y, groups, equation=0, seed=0)
    top = sel.effects[0]
    assert top["key"] == "heave_aero_lag"
    assert top["shape"] == pytest.approx(tau, rel=1e-3)       # polished off the grid
    assert top["coefficients"][0] == pytest.approx(-3.0, rel=1e-3)


def test_wrong_sign_dissipation_is_not_admitted(states):
    """Friction that feeds energy in is not friction: a residual that is +mu sign(h') is
    not explained as Coulomb friction (nor as negative quadratic damping)."""
    S, groups = states
    y = band(S, 0.5 * np.tanh(S["hd"] / 1e-3))
    sel = select(LIBRARY["flutter"], S, y, groups, equation=0, seed=0)
    keys = {e["key"]: e for e in sel.effects}
    assert "heave_friction" not in keys
    for k in ("heave_quadratic_damping", "heave_cubic_damping"):
        assert k not in keys or keys[k]["coefficients"][0] < 0


def test_jones_wake_states_solve_their_own_dynamics(states):
    """The unsteady-aerodynamics candidate's periodic wake states satisfy the hidden
    dynamics the refined model integrates (w'' = u - (c2 + c4) V/b w' - c2 c4 (V/b)^2 w)."""
    from ude_fit.models.library import JONES_AERO
    S, _ = states
    Z = JONES_AERO.states(S, None)
    n = S["n"]
    dW = np.fft.irfft(np.fft.rfft(Z[:, 0].reshape(-1, n), axis=1)
                      * 1j * np.arange(n // 2 + 1) * S["w"].reshape(-1, n)[:, :1],
                      n=n, axis=1).ravel()
    assert np.allclose(dW, Z[:, 1], atol=1e-9 * np.abs(Z[:, 1]).max())
    rate = JONES_AERO.rate(np, S, Z, None)
    d2W = np.fft.irfft(np.fft.rfft(Z[:, 1].reshape(-1, n), axis=1)
                       * 1j * np.arange(n // 2 + 1) * S["w"].reshape(-1, n)[:, :1],
                       n=n, axis=1).ravel()
    # exact for the band the samples carry: compare where the downwash has no harmonics
    # beyond the Nyquist limit (it is K-harmonic here)
    assert np.allclose(d2W, rate[:, 1], atol=1e-6 * np.abs(rate[:, 1]).max())


def test_a_learnt_correction_is_explained_like_a_residual(tmp_path):
    """`explain(target=U)`: the forces a correction supplies on the samples are explained
    with the mechanistic columns in; a correction that is a cubic heave spring is named so.
    And `ude-fit explain --model` runs on a saved UDE and reports its correction."""
    import jax
    import json

    from ude_fit import UDE, MLPCorrection, cli, flutter_qs, save_model
    from ude_fit.discovery.explain import explain
    from ude_fit.models.corrections import Scaling
    path = tmp_path / "f.h5"
    write_truth_campaign(path, "flutter", airspeeds=(18.0, 20.0, 22.0, 23.6))
    data = training_data(load([path], "flutter"))
    ys = np.asarray(data.ys)
    S = sample_states("flutter", ys, np.asarray(data.drive.param), np.asarray(data.drive.omega))
    U = np.stack([band(S, -4.0e5 * S["h"] ** 3), np.zeros(S["h"].size)], 1)
    ex = explain(data, "flutter", target=U, seed=0)
    assert ex.top()["key"] == "heave_cubic"
    assert ex.top()["coefficients"][0] == pytest.approx(-4.0e5, rel=0.02)

    sc = Scaling(np.zeros(5), np.ones(5), np.ones(2))
    model = UDE(flutter_qs(), MLPCorrection(5, 2, sc, key=jax.random.PRNGKey(0)))
    save_model(tmp_path / "u.eqx", model, role="ude")
    out = tmp_path / "why"
    assert cli.main(["explain", str(path), "--system", "flutter", "--model",
                     str(tmp_path / "u.eqx"), "--out", str(out), "--quiet"]) == 0
    doc = json.loads((out / "explanation.json").read_text())
    assert doc["correction"]["model"].endswith("u.eqx")
    assert len(doc["correction"]["equations"]) == 2
    assert "learnt correction U" in (out / "report.md").read_text()
