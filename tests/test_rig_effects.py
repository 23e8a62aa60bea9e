"""Undeclared effects and the user plugin change the rig's physics as documented.

Known truth here is static equilibrium, solved independently from the matrices
and the documented effect formulas (not from the compiled kernel), and free decay
compared with the clean rig.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import brentq, fsolve

from rig_sim.firmware.board import Board, RigOptions
from rig_sim.physics.flutter import FlutterParams, flutter_matrices

P = FlutterParams()


def settle(board: Board, seconds: float) -> np.ndarray:
    board.advance(int(seconds * board.rate))
    return board.true_state()


def quiet(kind="flutter", **kw) -> Board:
    return Board(RigOptions(kind=kind, sensor_noise=False, **kw))


def test_plugin_moment_gives_the_static_pitch_of_the_matrices(tmp_path):
    plug = tmp_path / "plug.py"
    plug.write_text(
        "import numpy as np\n"
        "def force(t, q, qdot, params):\n"
        "    # the rig passes its current airspeed: the moment is there only at 10 m/s\n"
        "    return np.array([0.0, 1.5 if params['airspeed'] == 10.0 else 0.0])\n")
    b = quiet(plugin=f"{plug}:force")
    b.set("parameter", 10.0)
    y = settle(b, 25.0)
    M, B, S = flutter_matrices(P, 10.0)

    def residual(q):   # S q + f_NL(q) = (0, M0, 0)
        return S @ q + np.array([0.0, P.k_alpha2 * q[1]**2 + P.k_alpha3 * q[1]**3, 0.0]) - [0, 1.5, 0]

    q = fsolve(residual, [0.0, 0.02, 0.0], xtol=1e-12)
    assert y[1] == pytest.approx(q[1], rel=1e-3)
    assert y[0] == pytest.approx(q[0], rel=1e-3, abs=1e-7)


def test_pitch_freeplay_dead_zone(tmp_path):
    plug = tmp_path / "plug.py"
    plug.write_text("def force(t, q, qd, p):\n    return [0.0, 0.8]\n")
    gap = 0.02
    b = quiet(plugin=f"{plug}:force", effects=[f"freeplay={gap}"])   # airspeed 0
    alpha = settle(b, 25.0)[1]

    def moment(a):     # k_a * deadzone(a) + k_a2 a^2 + k_a3 a^3 = M0
        dz = np.sign(a) * max(abs(a) - gap, 0.0)
        return P.k_alpha * dz + P.k_alpha2 * a**2 + P.k_alpha3 * a**3 - 0.8

    expected = brentq(moment, 0.0, 0.5)
    clean = brentq(lambda a: P.k_alpha * a + P.k_alpha2 * a**2 + P.k_alpha3 * a**3 - 0.8, 0, 0.5)
    assert alpha == pytest.approx(expected, rel=1e-3)
    assert alpha > clean + 0.005        # the gap shows


def test_cubic_heave_stiffness_static(tmp_path):
    plug = tmp_path / "plug.py"
    plug.write_text("def force(t, q, qd, p):\n    return [400.0, 0.0]\n")
    k3 = 2.0e5
    b = quiet(plugin=f"{plug}:force", effects=[f"heave_cubic={k3}"])
    h = settle(b, 25.0)[0]
    expected = brentq(lambda h: P.k_h * h + k3 * h**3 - 400.0, 0.0, 1.0)
    assert h == pytest.approx(expected, rel=1e-3)
    assert h < 400.0 / P.k_h * 0.97     # stiffer than the linear spring alone


def _decay_amplitude(effects) -> float:
    b = quiet(effects=effects)
    b.set("parameter", 5.0)
    b.set_true_state([0.05, 0, 0, 0, 0, 0])
    b.advance(int(3.0 * b.rate))
    ring = b.ring[: b.ic[9]].view(np.int16)[-2000:, 1] / 32767 * b.spec.full_scale[0]
    return float(np.max(np.abs(ring)))


@pytest.mark.parametrize("effect", ["heave_friction=3", "quadratic_damping=40"])
def test_dissipative_effects_speed_up_the_decay(effect):
    clean = _decay_amplitude([])
    damped = _decay_amplitude([effect])
    assert damped < 0.8 * clean


def test_oscillator_effects_are_applied():
    def amp(effects):
        b = quiet("oscillator", effects=effects)
        b.set("parameter", 1.0)
        b.set("frequency", 17.5)          # near the linear resonance: dissipation matters
        b.advance(int(3.0 * b.rate))
        return float(np.hypot(b.cmean[0, 1], b.cmean[0, 8]))

    clean = amp([])
    assert amp(["friction=0.02"]) < 0.95 * clean
    assert amp(["quadratic_damping=5"]) < 0.95 * clean
    assert amp(["cubic=5e7"]) < 0.95 * clean          # stiffer: further from resonance
    assert amp(["freeplay=0.0005"]) < 0.5 * clean     # softer: the resonance moves away


def test_effects_are_invisible_in_the_register_map():
    from rig_sim.device import register_map as M
    names = " ".join(r.name + " " + r.description for r in M.REGISTERS).lower()
    for word in ("freeplay", "friction", "cubic", "plugin", "effect"):
        assert word not in names
