"""A one-sided contact on the oscillator's tip: a spring that engages only above
x = 2 mm (not a catalogue form: the catalogue's freeplay is symmetric)."""
import numpy as np


def force(t, q, qdot, params):
    return np.array([-600.0 * max(q[0] - 0.002, 0.0)])
