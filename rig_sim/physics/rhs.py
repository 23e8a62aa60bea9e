"""Right-hand sides of both rigs, compiled with numba.

These are the single definition of the rigs' physics: the firmware kernel steps
them at the board rate, and the truth analysis (``rig_sim.physics.truth``) uses
them for equilibria, Hopf points and periodic orbits.

State layouts
  flutter:    y = (h, alpha, w, h', alpha', w'), kernel params from flutter_kernel_params
  oscillator: y = (x, x', i),                    kernel params from oscillator_kernel_params
Effect vector slots: see effects.py.
"""

from __future__ import annotations

import numpy as np
from numba import njit

# Smoothing velocities of Coulomb friction (tanh(v / v_s)); small enough that the
# friction is sign-like over the orbits of interest, large enough that RK4 at the
# board rate stays stable.
HEAVE_FRICTION_VS = 1e-3   # m/s
PITCH_FRICTION_VS = 1e-2   # rad/s


@njit(cache=True, inline="always")
def _clip(v, g):
    if v > g:
        return g
    if v < -g:
        return -g
    return v


@njit(cache=True)
def flutter_deriv(y, dy, f_heave, m_pitch, K, E):
    """dy = f(y) for the unsteady aerofoil with external heave force and pitch moment.

    K: M^-1 (0:9), B (9:18), S (18:27), k_a2, k_a3, k_a, k_h (27:31).
    """
    h, al, w = y[0], y[1], y[2]
    hd, ad, wd = y[3], y[4], y[5]
    # generalised forces on the right-hand side: F - B q' - S q - f_NL - effects
    r0 = f_heave - (K[9] * hd + K[10] * ad + K[11] * wd) - (K[18] * h + K[19] * al + K[20] * w)
    r1 = m_pitch - (K[12] * hd + K[13] * ad + K[14] * wd) - (K[21] * h + K[22] * al + K[23] * w)
    r1 -= K[27] * al * al + K[28] * al * al * al
    r2 = -(K[15] * hd + K[16] * ad + K[17] * wd) - (K[24] * h + K[25] * al + K[26] * w)
    if E[0] > 0.0:   # freeplay: the linear pitch spring sees the dead-zone angle
        r1 += K[29] * _clip(al, E[0])
    if E[1] > 0.0:
        r0 -= E[1] * np.tanh(hd / HEAVE_FRICTION_VS)
    if E[2] > 0.0:
        r1 -= E[2] * np.tanh(ad / PITCH_FRICTION_VS)
    if E[3] > 0.0:
        r0 -= E[3] * h * h * h
    if E[4] > 0.0:
        r0 -= E[4] * abs(hd) * hd
    if E[5] > 0.0:
        r1 -= E[5] * abs(ad) * ad
    dy[0] = hd
    dy[1] = ad
    dy[2] = wd
    dy[3] = K[0] * r0 + K[1] * r1 + K[2] * r2
    dy[4] = K[3] * r0 + K[4] * r1 + K[5] * r2
    dy[5] = K[6] * r0 + K[7] * r1 + K[8] * r2


@njit(cache=True)
def oscillator_deriv(y, dy, base_acc, f_ext, K, E, mass):
    """dy = f(y) for the oscillator; base_acc in m/s^2, f_ext an extra force in N."""
    x, xd, cur = y[0], y[1], y[2]
    x2 = x * x
    acc = -K[0] * xd - K[1] * x - x * x2 * (K[2] + x2 * (K[3] + x2 * K[4]))
    acc += K[6] * cur + K[5] * base_acc
    f = f_ext
    if E[0] > 0.0:
        acc += K[1] * _clip(x, E[0])
    if E[1] > 0.0:
        f -= E[1] * np.tanh(xd / HEAVE_FRICTION_VS)
    if E[3] > 0.0:
        f -= E[3] * x * x2
    if E[4] > 0.0:
        f -= E[4] * abs(xd) * xd
    acc += f / mass
    dy[0] = xd
    dy[1] = acc
    dy[2] = -K[7] * cur - K[8] * xd
