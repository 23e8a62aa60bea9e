"""AUTO-07p continuation reference for the quasi-steady flutter model (tests/auto07p_reference.py).

Checks AUTO's Hopf point against an independent numpy eigenvalue computation and that the fold
of limit cycles is found (and agrees with a scipy shooting computation).  Skipped, with the
reason, only when AUTO-07p cannot be built/run here (``.ci/auto07p_install.sh`` installs it).
"""

from __future__ import annotations

import pytest

from tests.auto07p_reference import (NOMINAL, auto_available, auto_flutter_reference,
                                     auto_unavailable_reason, eigen_hopf)

import jax  # noqa: E402  (after the imports above, before any array)

jax.config.update("jax_enable_x64", True)       # ude_fit computes in float64 (see ude_fit docs)

pytestmark = pytest.mark.skipif(not auto_available(),
                                reason=f"AUTO-07p unavailable: {auto_unavailable_reason()}")

# Fold of limit cycles of the nominal model from an independent computation: single shooting
# (scipy DOP853, rtol 1e-13) on orbits parametrised by max(alpha), minimising V over that
# amplitude with Brent's method.  Agrees with AUTO to ~1e-8 relative or better.
SHOOTING_FOLD_V = 15.851281378336
SHOOTING_FOLD_H_HALF_P2P = 0.0432511640
SHOOTING_FOLD_FREQ_HZ = 2.279602517585


@pytest.fixture(scope="module")
def nominal():
    return auto_flutter_reference(NOMINAL, v_range=(5.0, 40.0))


def test_hopf_matches_eigenvalues(nominal):
    V_h, f_h = eigen_hopf(NOMINAL, (5.0, 40.0))
    assert nominal["hopf_V"] == pytest.approx(V_h, rel=1e-6)
    assert nominal["hopf_freq_hz"] == pytest.approx(f_h, rel=1e-6)
    assert nominal["all_hopf_V"] == [nominal["hopf_V"]]
    assert nominal["origin_stable_at_v_min"] is True
    assert nominal["auto_version"].startswith("AUTO-07p")


def test_fold_found(nominal):
    assert nominal["hopf_subcritical"] is True
    assert nominal["fold_V"] is not None
    assert 5.0 < nominal["fold_V"] < nominal["hopf_V"]
    # mesh convergence: NTST=60 vs NTST=120 (NCOL=4)
    assert nominal["fold_rel_change"] < 1e-8
    assert nominal["fold_amplitude_h_coarse"] == pytest.approx(nominal["fold_amplitude_h"],
                                                               rel=1e-7)
    assert nominal["fold_V"] == pytest.approx(SHOOTING_FOLD_V, rel=1e-7)
    assert nominal["fold_amplitude_h"] == pytest.approx(SHOOTING_FOLD_H_HALF_P2P, rel=1e-6)
    assert nominal["fold_freq_hz"] == pytest.approx(SHOOTING_FOLD_FREQ_HZ, rel=1e-7)
    # first-harmonic heave amplitude is close to, but not the same as, half peak-to-peak
    assert nominal["fold_amplitude_h_first_harmonic"] == pytest.approx(
        nominal["fold_amplitude_h"], rel=1e-3)


def test_supercritical_variant_has_no_fold():
    # Without the quadratic pitch stiffness the (hardening) Hopf point is supercritical.
    p = dict(NOMINAL, k_alpha2=0.0)
    r = auto_flutter_reference(p, v_range=(5.0, 40.0))
    assert r["hopf_V"] == pytest.approx(eigen_hopf(p)[0], rel=1e-6)
    assert r["hopf_subcritical"] is False
    assert r["fold_V"] is None and r["fold_amplitude_h"] is None


# ---- ude_fit's own continuation against AUTO-07p --------------------------------------------

VARIANT = dict(NOMINAL, c_h=20.0, k_alpha2=600.0, k_alpha3=3000.0)


@pytest.fixture(scope="module")
def variant():
    return auto_flutter_reference(VARIANT, v_range=(5.0, 40.0))


@pytest.mark.parametrize("which", ["nominal", "variant"])
def test_ude_fit_continuation_matches_auto(which, nominal, variant):
    import numpy as np

    from ude_fit import UDE, flutter_qs, hopf_point, trace_flutter
    params, ref = (NOMINAL, nominal) if which == "nominal" else (VARIANT, variant)
    model = UDE(flutter_qs(**params))
    hopf = hopf_point(model, (5.0, 40.0))
    assert hopf["param"] == pytest.approx(ref["hopf_V"], rel=1e-4)
    assert hopf["frequency"] == pytest.approx(ref["hopf_freq_hz"], rel=1e-4)
    # the first Lyapunov coefficient's sign: AUTO's family leaves its HB towards lower V
    # exactly when the point is subcritical
    from ude_fit.analysis.criticality import hopf_criticality
    assert hopf_criticality(model, (5.0, 40.0)).subcritical is ref["hopf_subcritical"]
    branch = trace_flutter(model, v_range=(5.0, 40.0), amp_max=0.12,
                           scales=np.array([0.02, 0.1, 0.3, 1.5]))
    assert len(branch.folds) == 1
    assert branch.folds[0]["param"] == pytest.approx(ref["fold_V"], rel=1e-4)
    # the fold's first-harmonic heave amplitude as well
    assert branch.folds[0]["amplitude"] == pytest.approx(
        ref["fold_amplitude_h_first_harmonic"], rel=1e-3)
    # stability changes exactly at the fold: unstable between Hopf and fold, stable beyond
    k = int(np.argmin(branch.param))
    assert not branch.stable[1:k - 1].any() and branch.stable[k + 2:].all()
