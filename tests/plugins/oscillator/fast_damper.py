"""A damper on the oscillator's tip that engages only on fast motion in +x (x' > 0.3
m/s): direction- and speed-dependent damping, not a catalogue form."""
import numpy as np


def force(t, q, qdot, params):
    return np.array([-1.5 * max(qdot[0] - 0.3, 0.0)])
