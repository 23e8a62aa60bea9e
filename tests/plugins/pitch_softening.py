"""A pitch spring that softens beyond |alpha| = 0.06 rad (half its stiffness lost)."""
import numpy as np


def force(t, q, qdot, params):
    a = q[1]
    return np.array([0.0, 30.0 * (a - min(max(a, -0.06), 0.06))])
