"""A velocity-saturating damping force on the oscillator's tip: linear at low speed,
levelling off above 0.3 m/s (not a catalogue form: the catalogue's Coulomb friction
saturates at 1 mm/s, its polynomial dampings grow without bound)."""
import math
import numpy as np


def force(t, q, qdot, params):
    return np.array([-0.5 * 0.3 * math.tanh(qdot[0] / 0.3)])
