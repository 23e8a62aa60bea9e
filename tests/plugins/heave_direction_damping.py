"""Direction-dependent heave damping: quadratic, acting only while the wing moves up."""
import numpy as np


def force(t, q, qdot, params):
    v = max(qdot[0], 0.0)
    return np.array([-30.0 * v * v, 0.0])
