"""A one-sided heave stop: a spring that engages only above h = 0.05 m (not a catalogue
form)."""
import numpy as np


def force(t, q, qdot, params):
    return np.array([-3000.0 * max(q[0] - 0.05, 0.0), 0.0])
