"""The rigs' ground truth: Hopf point, limit-cycle branch and S-curves.

The continuation in ``rig_sim.physics.truth`` is the reference the campaign tests
will judge CBC against, so here it is itself checked against independent facts:
published numbers for the aerofoil's Hopf point, the linearisation of the compiled
right-hand side, and direct time simulation with scipy's adaptive DOP853 (not the
shooting code's fixed-step integrator) of the same right-hand sides.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from rig_sim.physics.flutter import FlutterParams, flutter_jacobian, flutter_kernel_params
from rig_sim.physics.oscillator import OscillatorParams, oscillator_kernel_params
from rig_sim.physics.rhs import flutter_deriv, oscillator_deriv
from rig_sim.physics.truth import (
    first_harmonic,
    flutter_equilibrium_eigenvalues,
    flutter_hopf,
    flutter_lco_at,
    flutter_lco_branch,
    flutter_orbit_at,
    oscillator_amplitude_at,
    oscillator_scurve,
)

FP = FlutterParams()
OP = OscillatorParams()
V_BISTABLE = 23.0          # below the Hopf point, above the fold
TESTED_FREQS = (20.0, 23.0, 26.0)


# ----------------------------------------------------------------------------- helpers

def _flutter_sim(V, y0, t_end):
    K = flutter_kernel_params(FP, V)
    E = np.zeros(6)

    def f(t, y):
        dy = np.empty(6)
        flutter_deriv(y, dy, 0.0, 0.0, K, E)
        return dy

    sol = solve_ivp(f, (0.0, t_end), y0, method="DOP853", rtol=1e-9, atol=1e-12,
                    dense_output=True)
    assert sol.success
    return sol


def _measured_heave_amplitude(sol, t_end, window=6.0):
    """First-harmonic heave amplitude over the last full period of a simulation, the
    period measured from the simulation's own upward mean crossings."""
    t = np.linspace(t_end - window, t_end, 20001)
    h = sol.sol(t)[0]
    h = h - h.mean()
    up = np.nonzero((h[:-1] < 0) & (h[1:] >= 0))[0]
    if up.size < 3:
        return float(np.max(np.abs(h)))   # no oscillation left: report the size of what is
    # linear interpolation of the crossing times
    tc = t[up] - h[up] * (t[up + 1] - t[up]) / (h[up + 1] - h[up])
    ts = np.linspace(tc[-2], tc[-1], 1024, endpoint=False)
    return first_harmonic(sol.sol(ts)[0])[0]


def _oscillator_sim(freq, Phi, y0, periods):
    K = oscillator_kernel_params(OP)
    E = np.zeros(6)
    w = 2.0 * np.pi * freq

    def f(t, y):
        dy = np.empty(3)
        oscillator_deriv(y, dy, Phi * np.cos(w * t), 0.0, K, E, OP.mass)
        return dy

    T = 1.0 / freq
    sol = solve_ivp(f, (0.0, periods * T), y0, method="DOP853", rtol=1e-9, atol=1e-12,
                    dense_output=True)
    assert sol.success
    ts = np.linspace((periods - 1) * T, periods * T, 512, endpoint=False)
    return first_harmonic(sol.sol(ts)[0])[0]


# ---------------------------------------------------------------------------- fixtures

@pytest.fixture(scope="module")
def branch():
    return flutter_lco_branch(FP, V_max=26.0)


@pytest.fixture(scope="module")
def scurves():
    return {f: oscillator_scurve(f, OP) for f in TESTED_FREQS}


# ----------------------------------------------------------------------------- aerofoil

def test_rhs_linearisation_is_flutter_jacobian():
    """The compiled rhs and flutter.py's matrices describe the same linear system."""
    for V in (10.0, 23.95, 30.0):
        K = flutter_kernel_params(FP, V)
        E = np.zeros(6)
        J = np.empty((6, 6))
        dp, dm = np.empty(6), np.empty(6)
        for j in range(6):
            e = np.zeros(6)
            e[j] = 1e-7
            flutter_deriv(e, dp, 0.0, 0.0, K, E)
            flutter_deriv(-e, dm, 0.0, 0.0, K, E)
            J[:, j] = (dp - dm) / 2e-7
        ref = flutter_jacobian(FP, V)
        assert np.allclose(J, ref, rtol=1e-6, atol=1e-6 * np.abs(ref).max())


def test_hopf_point():
    V_h, f_h = flutter_hopf(FP)
    assert abs(V_h - 23.95) < 0.1
    assert abs(f_h - 2.416) < 0.02
    # it is a genuine crossing: stable just below, unstable just above
    assert np.max(flutter_equilibrium_eigenvalues(V_h - 0.05, FP).real) < 0
    assert np.max(flutter_equilibrium_eigenvalues(V_h + 0.05, FP).real) > 0


def test_linear_effects_do_not_move_hopf_but_freeplay_does():
    """Effects that vanish to first order at rest leave the linearisation alone."""
    V_h, f_h = flutter_hopf(FP)
    V_c, f_c = flutter_hopf(FP, {"heave_cubic": 1e6, "quadratic_damping": 50.0})
    assert abs(V_c - V_h) < 1e-6 and abs(f_c - f_h) < 1e-6
    # freeplay removes the linear pitch spring near rest: a different linear system
    ev_fp = flutter_equilibrium_eigenvalues(15.0, FP, {"freeplay": 0.01})
    ev = flutter_equilibrium_eigenvalues(15.0, FP)
    assert np.max(np.abs(np.sort_complex(ev_fp) - np.sort_complex(ev))) > 1.0


def test_branch_is_subcritical_with_one_fold(branch):
    V_h, _ = flutter_hopf(FP)
    assert branch.hopf[0] == pytest.approx(V_h)
    assert len(branch.folds) == 1
    fold = branch.folds[0]
    assert fold["V"] < V_BISTABLE < V_h          # bistable window contains 23 m/s
    k = fold["index"]
    # unstable orbits from the Hopf point to the fold, stable ones after it
    assert not branch.stable[: k + 1].any()
    assert branch.stable[k + 2:].all()
    assert np.all(branch.V[: k + 1] <= V_h + 1e-9)
    assert np.all(branch.V[: k + 1] >= fold["V"] - 1e-9)
    # amplitude goes to zero at the Hopf point along the unstable branch
    assert branch.heave_amp[0] < 0.005 and abs(branch.V[0] - V_h) < 0.05
    # traced around the fold out to 26 m/s on the stable branch
    assert branch.V[-1] >= 26.0 and branch.stable[-1]
    # at the fold a second Floquet multiplier passes through +1
    assert abs(fold["floquet_max"] - 1.0) < 1e-3


def test_lco_at_matches_dense_branch(branch):
    """The refined amplitude at exact V agrees with interpolating the traced branch."""
    stable = branch.stable
    for V in (21.0, 22.5, 25.5):
        amp = flutter_lco_at(V, branch)["stable"]
        interp = np.interp(V, branch.V[stable], branch.heave_amp[stable])
        assert amp == pytest.approx(interp, rel=2e-3)


def test_bistable_at_23_by_direct_simulation(branch):
    V = V_BISTABLE
    # rest is linearly stable ...
    assert np.max(flutter_equilibrium_eigenvalues(V, FP).real) < 0
    # ... and a stable limit cycle coexists with it, separated by an unstable one
    amps = flutter_lco_at(V, branch)
    assert amps["stable"] is not None and amps["unstable"] is not None
    assert amps["unstable"] < amps["stable"]
    orbits = {o["stable"]: o for o in flutter_orbit_at(V, branch)}
    stable, unstable = orbits[True], orbits[False]

    # started 3 % off the stable cycle, the simulation settles on its amplitude
    sol = _flutter_sim(V, 1.03 * stable["state"], 40.0)
    assert _measured_heave_amplitude(sol, 40.0) == pytest.approx(amps["stable"], rel=0.01)

    # a small disturbance (1 mm heave) dies out
    y0 = np.zeros(6)
    y0[0] = 1e-3
    sol = _flutter_sim(V, y0, 60.0)
    assert _measured_heave_amplitude(sol, 60.0) < 2e-4

    # the unstable cycle is the threshold: 10 % inside it decays, 10 % outside it
    # grows to the stable cycle
    sol = _flutter_sim(V, 0.9 * unstable["state"], 60.0)
    assert _measured_heave_amplitude(sol, 60.0) < 0.1 * amps["unstable"]
    sol = _flutter_sim(V, 1.1 * unstable["state"], 60.0)
    assert _measured_heave_amplitude(sol, 60.0) == pytest.approx(amps["stable"], rel=0.01)


# --------------------------------------------------------------------------- oscillator

@pytest.mark.parametrize("freq", TESTED_FREQS)
def test_scurve_has_two_folds_and_unstable_middle(scurves, freq):
    c = scurves[freq]
    assert len(c.folds) == 2
    hi, lo = c.folds                      # traced from small Phi: jump-up fold first
    assert hi["Phi"] > lo["Phi"] > 0
    assert hi["amp"] < lo["amp"]
    assert hi["Phi"] < OP.shaker_limit and lo["Phi"] < OP.shaker_limit
    i, j = hi["index"], lo["index"]
    assert c.stable[: i + 1].all()                 # lower branch
    assert not c.stable[i + 1: j + 1].any()        # middle branch
    assert (c.floquet_max[i + 2: j] > 1.0).all()
    assert c.stable[j + 1:].all()                  # upper branch
    assert c.Phi[-1] >= OP.shaker_limit            # traced through to the shaker limit
    # at each fold the Floquet multiplier passes through +1
    assert abs(hi["floquet_max"] - 1.0) < 1e-3 and abs(lo["floquet_max"] - 1.0) < 1e-3


@pytest.mark.parametrize("freq", TESTED_FREQS)
def test_scurve_coexisting_orbits_by_direct_simulation(scurves, freq):
    c = scurves[freq]
    Phi = float(np.sqrt(c.folds[0]["Phi"] * c.folds[1]["Phi"]))
    branches = oscillator_amplitude_at(Phi, c)
    assert [s for _, s in branches] == [True, False, True]
    a_low, a_mid, a_up = (a for a, _ in branches)
    assert a_low < a_mid < a_up
    # from rest: the lower branch
    measured_low = _oscillator_sim(freq, Phi, np.zeros(3), 150)
    # tip released at the upper branch's amplitude, at rest, as the forcing peaks
    measured_up = _oscillator_sim(freq, Phi, np.array([a_up, 0.0, 0.0]), 150)
    assert measured_low == pytest.approx(a_low, rel=0.01)
    assert measured_up == pytest.approx(a_up, rel=0.01)
    assert measured_up > 2.0 * measured_low
