"""Position-dependent heave damping: a damper whose coefficient grows with the square of
the heave displacement (F = -c h^2 h'), doubling the heave damping at |h| = 0.05 m."""
import numpy as np


def force(t, q, qdot, params):
    return np.array([-6000.0 * q[0] * q[0] * qdot[0], 0.0])
