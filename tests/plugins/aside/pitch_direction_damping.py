"""Held aside until the end: direction-dependent pitch damping (nose-up motion only)."""
import numpy as np


def force(t, q, qdot, params):
    w = max(qdot[1], 0.0)
    return np.array([0.0, -0.5 * w * w])
