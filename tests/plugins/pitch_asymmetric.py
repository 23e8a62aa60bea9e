"""Asymmetric pitch stiffness: stiffening for nose-up pitch only (alpha > 0)."""
import numpy as np


def force(t, q, qdot, params):
    a = max(q[1], 0.0)
    return np.array([0.0, -300.0 * a * a])
