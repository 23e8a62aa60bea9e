"""The locator (ude_fit/discovery/locate.py) and the describer (describe.py) on residuals
of known make-up: sinusoidal orbits of known amplitudes (states analytic), a mechanistic
part, a planted shape of one state (truth known), noise. Which equation and state, which
class, where: all known here."""

from __future__ import annotations

import numpy as np
import pytest

from ude_fit.discovery.describe import describe_shape
from ude_fit.discovery.locate import STATE_NAMES, locate_equation
from ude_fit.models.forms import located_states
from ude_fit.models.library import band_limited, effect

N_ORBITS, N = 20, 32
NOISE = 0.5


def _orbits(seed):
    rng = np.random.default_rng(seed)
    th = np.linspace(0, 2 * np.pi, N, endpoint=False)[None]
    A, B = rng.uniform(0.2, 1.0, (N_ORBITS, 1)), rng.uniform(0.1, 0.5, (N_ORBITS, 1))
    ph, w = rng.uniform(0, 2 * np.pi, (N_ORBITS, 1)), rng.uniform(5, 8, (N_ORBITS, 1))
    S = {"h": (A * np.cos(th)).ravel(), "hd": (-A * w * np.sin(th)).ravel(),
         "al": (B * np.cos(th + ph)).ravel(), "ad": (-B * w * np.sin(th + ph)).ravel(),
         "V": np.repeat(rng.uniform(10, 20, N_ORBITS), N), "w": np.repeat(w.ravel(), N),
         "n": N, "b": 0.15, "a": -0.5}
    return S, rng


def _located(planted, seed=1, states=None):
    S, rng = _orbits(seed)
    base = np.stack([S["hd"], S["h"]], 1)
    g = band_limited(planted(S)[:, None], N)[:, 0]        # what K-harmonic orbits carry
    y = base @ np.array([-1.0, -100.0]) + g + NOISE * rng.standard_normal(len(g))
    loc = locate_equation(S, y, np.repeat(np.arange(N_ORBITS), N), equation=0, base=base,
                          states=states or STATE_NAMES["flutter"], per_orbit=N)
    loc.name = "heave"
    return loc, S


CASES = [
    # planted shape, state, class key, threshold
    (lambda S: -50 * np.maximum(S["h"] - 0.5, 0), "h", "above", 0.5),
    (lambda S: 40 * np.minimum(S["h"] + 0.4, 0), "h", "below", -0.4),
    (lambda S: -3 * np.maximum(S["hd"], 0), "hd", "kink", None),
    (lambda S: -60 * (S["al"] - np.clip(S["al"], -0.2, 0.2)), "al", "beyond", 0.2),
]


@pytest.mark.parametrize("case", range(len(CASES)))
def test_locates_the_state_and_names_the_class(case):
    planted, state, cls, d = CASES[case]
    loc, S = _located(planted)
    sig = loc.significant
    assert [s.state for s in sig] == [state], [(s.name, s.cv_gain / s.cv_gain_se)
                                               for s in loc.shapes]
    desc = describe_shape("flutter", loc, sig[0], S)
    assert desc.named and desc.best.key == f"heave.{STATE_NAMES['flutter'][state]}.{cls}"
    if d is not None:
        assert desc.best.shape == pytest.approx(d, abs=0.1 * np.ptp(S[state]))
    # the band covers the truth's nonlinear part: checked where the planted form is known
    s = sig[0]
    truth = planted({**S, state: s.grid})
    L = np.stack([np.ones_like(s.grid), s.grid], 1)
    dev = lambda v: v - L @ np.linalg.lstsq(L, v, rcond=None)[0]
    inside = np.abs(dev(s.value) - dev(truth)) <= 3 * s.band + 0.05 * np.ptp(truth)
    assert inside.mean() > 0.8


def test_a_catalogue_term_wins_when_it_fits_as_well():
    loc, S = _located(lambda S: -100 * S["h"] ** 3)
    desc = describe_shape("flutter", loc, loc.significant[0], S)
    assert desc.best.key == "heave_cubic" and desc.best.catalogue
    assert desc.best.coefficients[0] == pytest.approx(-100, rel=0.2)


def test_a_shape_no_class_fits_is_still_located_and_said_so():
    loc, S = _located(lambda S: -20 * np.exp(-((S["h"] - 0.3) / 0.1) ** 2))
    assert [s.state for s in loc.significant] == ["h"]
    desc = describe_shape("flutter", loc, loc.significant[0], S)
    assert not desc.named
    assert desc.phrase().startswith("an effect in heave depending on h, shaped like")
    assert desc.contenders[0].key == "spline"


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_noise_alone_is_no_shape(seed):
    loc, _ = _located(lambda S: 0 * S["h"], seed=seed)
    assert loc.significant == []


def test_a_located_form_is_an_effect_the_refined_model_can_carry():
    e = effect("flutter", "heave.h.above")
    assert e.equation == 0 and e.terms == ("max(h - d, 0)",)
    S = {"h": np.array([-0.1, 0.2, 0.5])}
    assert e.formula(np, S, 0.1)[:, 0] == pytest.approx([0.0, 0.1, 0.4])
    with pytest.raises(ValueError, match="unknown effect"):
        effect("flutter", "heave.h.wobble")


def test_a_damping_that_grows_with_position_is_a_shape_of_the_position_times_the_velocity():
    """-c h^2 h' is no shape of one state; as the coefficient of h' it is a shape of h."""
    loc, S = _located(lambda S: -30 * S["h"] ** 2 * S["hd"],
                      states=located_states("flutter", 0))
    sig = loc.significant
    assert sig[0].state == "h*hd" and sig[0].name == "h_dot(h)"
    desc = describe_shape("flutter", loc, sig[0], S)
    assert desc.best.key == "heave.h_dot(h).quadratic", [c.key for c in desc.contenders[:4]]
    assert desc.best.coefficients[0] == pytest.approx(-30, rel=0.1)
    assert desc.phrase() == "damping of h_dot depending on h: coefficient ~ h^2"
    e = effect("flutter", "heave.h_dot(h).quadratic")
    assert e.terms == ("h^2 h_dot",)
    assert e.formula(np, {"h": np.array([0.5, 2.0]), "hd": np.array([2.0, -1.0])}, None)[:, 0] \
        == pytest.approx([0.5, -4.0])


def test_no_position_dependent_damping_in_noise_or_in_a_shape_of_one_state():
    for planted in (lambda S: 0 * S["h"], lambda S: -50 * np.maximum(S["h"] - 0.5, 0)):
        loc, _ = _located(planted, states=located_states("flutter", 0))
        assert not any("*" in s.state for s in loc.significant), \
            [(s.state, s.p_value) for s in loc.significant]
