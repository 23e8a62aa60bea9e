"""Closed loop on the board: a target equal to the true unstable limit cycle holds
the rig on it with small control effort; the same target far from it needs large
effort. Truth: the unstable orbit from the rig's own model (shooting + continuation
in rig_sim.physics.truth), resampled here by an independent scipy integration."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from rig_sim.firmware import layout as L
from rig_sim.firmware.board import Board, RigOptions
from rig_sim.physics.flutter import FlutterParams, flutter_kernel_params
from rig_sim.physics.rhs import flutter_deriv
from rig_sim.physics.truth import flutter_lco_branch, flutter_orbit_at

V = 23.0          # inside the bistable range (below the Hopf point, above the fold)
P = FlutterParams()


@pytest.fixture(scope="module")
def unstable_orbit():
    branch = flutter_lco_branch(V_max=24.5)
    orbits = [o for o in flutter_orbit_at(V, branch) if not o["stable"]]
    assert len(orbits) == 1
    orb = orbits[0]
    K = flutter_kernel_params(P, V)
    E = np.zeros(6)

    def f(t, y):
        dy = np.empty(6)
        flutter_deriv(y, dy, 0.0, 0.0, K, E)
        return dy

    T = orb["period"]
    t = np.linspace(0.0, T, 2049)[:-1]
    sol = solve_ivp(f, (0.0, T), orb["state"], t_eval=t, rtol=1e-11, atol=1e-13, method="DOP853")
    h = sol.y[0]
    theta = 2 * np.pi * t / T
    coef = [h.mean()] + [2 * np.mean(h * np.cos(k * theta)) for k in range(1, 8)] \
        + [2 * np.mean(h * np.sin(k * theta)) for k in range(1, 8)]
    return orb, np.array(coef)


def _run(orb, coef, armed=True, phase_locked=False, seconds=20.0, start_scale=1.0):
    b = Board(RigOptions(kind="flutter", seed=1))            # sensor noise on, sigma = 0
    b.set("parameter", V)
    b.set("frequency", 1.0 / orb["period"])
    b.set("phase_mode", 1.0 if phase_locked else 0.0)
    b.set("kp", 2000.0)
    b.set("kd", 40.0)
    b.set("watchdog_timeout", 60.0)
    for name, c in zip(["target_a0"] + [f"target_a{k}" for k in range(1, 8)]
                       + [f"target_b{k}" for k in range(1, 8)], coef):
        b.set(name, float(c))
    b.set_true_state(start_scale * orb["state"])              # on the orbit, at target phase 0
    if armed:
        b.arm()
    n = int(seconds * b.rate)
    b.sim_time_at_heartbeat = 0.0
    b.advance(n - 4000)
    tail = []
    for _ in range(4):                                        # last 0.8 s, sample by sample
        b.advance(1000)
        tail.append(b.ring[(b.ic[L.IC_RING_HEAD] - 1000 + np.arange(1000)) % L.RING_CAP].view(np.int16))
    rec = np.concatenate(tail).astype(float)
    h = rec[:, L.REC_X] / 32767 * b.spec.full_scale[0]
    u = rec[:, L.REC_CONTROL] / 32767 * b.spec.saturation
    amp = float(np.hypot(b.cmean[0, 1], b.cmean[0, 8]))
    return h, u, amp


def test_the_true_unstable_cycle_is_held_with_small_effort(unstable_orbit):
    orb, coef = unstable_orbit
    h, u, amp = _run(orb, coef, start_scale=1.05)              # starts 5 % off, is pulled back
    effort = np.sqrt(np.mean(u**2)) / np.sqrt(np.mean((P.k_h * h) ** 2))
    assert effort < 0.01, effort                               # under 1 % of the spring force
    assert amp == pytest.approx(orb["heave_amp"], rel=0.01)    # and it is on the orbit


def test_phase_locked_target_also_holds_it(unstable_orbit):
    orb, coef = unstable_orbit
    locked = np.zeros(15)
    locked[0] = coef[0]
    locked[1] = orb["heave_amp"]                                # the paper's A0 + A1 cos(phi)
    h, u, amp = _run(orb, locked, phase_locked=True)
    effort = np.sqrt(np.mean(u**2)) / np.sqrt(np.mean((P.k_h * h) ** 2))
    assert effort < 0.02, effort
    assert amp == pytest.approx(orb["heave_amp"], rel=0.02)


def test_a_target_far_from_the_cycle_needs_large_effort(unstable_orbit):
    orb, coef = unstable_orbit
    _, u_on, _ = _run(orb, coef)
    # three times the unstable cycle: between it and the stable one, where the
    # open-loop orbit would grow; the controller has to hold it back all the time
    h, u, amp = _run(orb, 3.0 * coef)
    effort = np.sqrt(np.mean(u**2)) / np.sqrt(np.mean((P.k_h * h) ** 2))
    assert effort > 0.1, effort
    assert np.sqrt(np.mean(u**2)) > 20 * np.sqrt(np.mean(u_on**2))


def test_without_control_the_rig_leaves_the_unstable_cycle(unstable_orbit):
    orb, coef = unstable_orbit
    h, u, amp = _run(orb, coef, armed=False, start_scale=1.05)   # 5 % off the cycle
    assert np.all(u == 0.0)
    assert abs(amp - orb["heave_amp"]) > 0.1 * orb["heave_amp"]
