"""The board's on-board Fourier estimator against signals with known coefficients."""

import numpy as np
import pytest

from rig_sim.firmware.board import Board, RigOptions


@pytest.mark.parametrize("freq", [2.37, 20.0, 23.0, 26.0])   # 23 Hz at 10 kHz: 434.78 samples a period
def test_a_known_cosine_is_estimated_exactly(freq):
    b = Board(RigOptions(kind="oscillator", sensor_noise=False))
    b.set("frequency", freq)
    b.set("parameter", 7.5)                   # base acceleration 7.5 cos(wt): the excitation channel
    b.advance(int(1.0 * b.rate))
    b.reset_averages()
    b.advance(int(2.0 * b.rate))
    exc = b.cmean[2]
    assert np.hypot(exc[1], exc[8]) == pytest.approx(7.5, rel=1e-6)
    # leakage into DC and harmonics under 2e-5 of the amplitude (the old, unsplit period
    # boundary leaked ~4e-4 of it into each harmonic)
    assert abs(exc[0]) < 1e-6 and np.all(np.abs(exc[2:8]) < 1.5e-4) and np.all(np.abs(exc[9:]) < 1.5e-4)
    assert b.fmean[0] == pytest.approx(freq, rel=1e-9)
    assert b.cvar[2, 1] < 1e-12               # the same every period
