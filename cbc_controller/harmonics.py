"""The board's Fourier series, 15 coefficients (a0, a1..a7, b1..b7) per channel: the numbers
the engine reads and the plans reason about."""

from __future__ import annotations

import math

from rig_sim.device import register_map as M

NH = M.NHARM                  # harmonics in the board's series


def amplitude(coef) -> float:
    """First-harmonic amplitude from the 15 coefficients (a0, a1..a7, b1..b7)."""
    return float(math.hypot(coef[1], coef[1 + NH]))
