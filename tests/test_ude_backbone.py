"""The Hopf normal-form backbone (ude_fit.analysis.backbone) against analytical results:
orbits sampled from a known amplitude equation give back its Hopf point, fold and
stabilities."""

import numpy as np
import pytest

from ude_fit.analysis.backbone import backbone_of, fit_backbone

# r' = r (m (V - VH) + a r^2 + b r^4): orbits at V = VH - (a r^2 + b r^4) / m
VH, M, A3, B5 = 24.0, 0.5, 400.0, -60000.0


def _orbits(r, m=M, a=A3, b=B5):
    r = np.asarray(r, float)
    V = VH - (a * r ** 2 + b * r ** 4) / m
    # Floquet exponent of the orbit: d/dr [r g(r)] at g = 0 is r g'(r) = 2 r^2 (a + 2 b r^2)
    stable = (a + 2 * b * r ** 2) < 0
    return V, r, stable


def _fold():
    # dV/d(r^2) = 0: r^2 = -a / (2 b); V = VH + a^2 / (4 b m)
    return VH + A3 ** 2 / (4 * B5 * M), np.sqrt(-A3 / (2 * B5))


def test_exact_normal_form_points_give_back_its_hopf_fold_and_stability():
    V, r, stable = _orbits(np.linspace(0.01, 0.09, 12))
    bb = fit_backbone(V, r, stable)
    vf, rf = _fold()
    assert bb.hopf == pytest.approx(VH, abs=1e-6)
    assert bb.fold == pytest.approx(vf, abs=1e-6)
    assert bb.fold_amplitude == pytest.approx(rf, rel=1e-6)
    assert bb.m_sign == 1
    assert np.array_equal(bb.stable(r), stable)
    # both orbits at an airspeed between the fold and the Hopf point, the smaller unstable
    v = 0.5 * (vf + VH)
    orbits = bb.orbits_at(v)
    assert [s for _, s in orbits] == [False, True]
    for amp, _ in orbits:
        assert VH - (A3 * amp ** 2 + B5 * amp ** 4) / M == pytest.approx(v, abs=1e-6)
    assert bb.orbits_at(vf - 0.1) == []                    # below the fold: rest only
    assert len(bb.orbits_at(VH + 0.1)) == 1                # beyond the Hopf point: one
    m = bb.metrics(V, r, stable).summary
    assert m.missed == 0 and m.branch_rms < 1e-6


def test_noisy_points_the_truth_within_the_reported_uncertainty():
    rng = np.random.default_rng(0)
    V, r, stable = _orbits(np.linspace(0.015, 0.085, 14))
    Vn = V + rng.normal(0, 0.05, V.size)
    rn = r * (1 + rng.normal(0, 0.01, r.size))
    bb = fit_backbone(Vn, rn, stable)
    vf, _ = _fold()
    assert abs(bb.hopf - VH) < 3 * bb.hopf_std() and bb.hopf_std() < 0.5
    assert abs(bb.fold - vf) < 3 * bb.fold_std()


def test_supercritical_form_has_no_fold_and_stable_orbits():
    V, r, stable = _orbits(np.linspace(0.01, 0.08, 8), a=-300.0, b=-1000.0)
    assert stable.all()
    bb = fit_backbone(V, r, stable)
    assert bb.fold is None and bb.fold_std() is None
    assert bb.hopf == pytest.approx(VH, abs=1e-6)
    assert bb.stable(r).all()
    assert len(bb.orbits_at(VH + 1.0)) == 1 and bb.orbits_at(VH - 1.0) == []


def test_labels_decide_the_sign_of_the_growth_rate():
    # the same curve, but the equilibrium stable *above* the Hopf point (m < 0): every
    # stability flips, which only the labels can tell
    V, r, stable = _orbits(np.linspace(0.01, 0.09, 10), m=-M, a=-A3, b=-B5)
    bb = fit_backbone(V, r, stable)
    assert bb.m_sign == -1 and np.array_equal(bb.stable(r), stable)
    # without labels the aerofoil's convention: the equilibrium stable below the Hopf point
    assert fit_backbone(V, r).m_sign == 1


def test_too_few_points_or_bad_input():
    V, r, _ = _orbits([0.02, 0.04, 0.06])
    assert fit_backbone(V, r) is None
    with pytest.raises(ValueError, match="positive"):
        fit_backbone([20.0, 21.0, 22.0, 23.0], [0.01, -0.02, 0.03, 0.04])
    with pytest.raises(ValueError, match="one length"):
        fit_backbone([20.0, 21.0], [0.01])


def test_forced_data_has_no_backbone():
    class Forced:
        system = "oscillator"
    assert backbone_of(Forced()) is None
