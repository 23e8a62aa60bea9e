"""Another configuration of a rig (``rig-sim serve --physics``): the board runs the
parameters it is given, and the aerofoil with its lag state switched off (c1 = c3 = 0) is
the quasi-steady model of the paper's appendix A.2, which ude_fit's mechanistic model
writes independently."""

from __future__ import annotations

import numpy as np
import pytest

from rig_sim.firmware.board import Board, RigOptions
from rig_sim.physics.configuration import ConfigurationError, configured_params
from rig_sim.physics.flutter import FlutterParams, flutter_jacobian

QUASI_STEADY = ("c1=0", "c3=0")


def test_the_given_values_replace_the_design_ones_and_nothing_else():
    p = configured_params("flutter", ["k_h=3000", "c1=0"])
    design = FlutterParams().as_dict()
    assert p.k_h == 3000.0 and p.c1 == 0.0
    assert {k: v for k, v in p.as_dict().items() if k not in ("k_h", "c1")} == {
        k: v for k, v in design.items() if k not in ("k_h", "c1")}
    assert configured_params("oscillator", ["zeta=0.01"]).zeta == 0.01
    with pytest.raises(ConfigurationError, match="not a parameter of the oscillator"):
        configured_params("oscillator", ["k_h=1"])


def test_the_board_runs_the_configuration_it_is_started_with():
    """Free decay from the same pitch on the design rig and on the quasi-steady one part
    within a period (their linearisations differ), and the quasi-steady board's own
    parameters are the ones given."""
    states = []
    for physics in ((), QUASI_STEADY):
        b = Board(RigOptions(kind="flutter", sensor_noise=False, physics=list(physics)))
        b.set("parameter", 20.0)
        b.set_true_state(np.array([0.0, 0.05, 0.0, 0.0, 0.0, 0.0]))
        b.advance(int(0.4 * b.rate))
        states.append(b.true_state())
        assert b.params == configured_params("flutter", physics)
    assert not np.allclose(states[0][:2], states[1][:2], rtol=1e-3, atol=1e-6)


@pytest.mark.parametrize("V", [10.0, 20.0, 24.0])
def test_without_its_lag_the_aerofoil_is_the_quasi_steady_model(V):
    """The quasi-steady rig's eigenvalues at rest are the mechanistic model's (with the
    design values), plus those of the lag state, which no longer acts on the wing."""
    from ude_fit.models.mechanistic import flutter_qs

    p = configured_params("flutter", QUASI_STEADY)
    rig = np.linalg.eigvals(flutter_jacobian(p, V))
    m = flutter_qs(**{k: getattr(p, k) for k in ("c_h", "c_alpha", "k_h", "k_alpha")})
    K = np.diag([p.k_h, p.k_alpha]) + np.asarray(m.aero_stiffness(V))
    C = np.diag([p.c_h, p.c_alpha]) + np.asarray(m.aero_damping(V))
    Minv = np.linalg.inv(np.asarray(m.mass(V)))
    J = np.block([[np.zeros((2, 2)), np.eye(2)], [-Minv @ K, -Minv @ C]])
    # (the 6 x 6 matrix's one-way coupling into the lag state is strong and far from
    # normal: LAPACK's eigenvalues of it agree with the 4 x 4 ones to about 1e-7)
    for lam in np.linalg.eigvals(J):
        assert np.min(np.abs(rig - lam)) < 1e-6 * abs(lam)
    # the design rig's lag does act: its eigenvalues are not the quasi-steady ones
    design = np.linalg.eigvals(flutter_jacobian(FlutterParams(), V))
    assert max(np.min(np.abs(design - lam)) for lam in np.linalg.eigvals(J)) > 1e-3
