"""Ground-truth physics of the virtual rigs (hidden from any client)."""

from .effects import EFFECTS, EffectError, load_plugin, parse_effects
from .flutter import FlutterParams, flutter_jacobian, flutter_matrices
from .oscillator import OscillatorParams

__all__ = ["EFFECTS", "EffectError", "FlutterParams", "OscillatorParams",
           "flutter_jacobian", "flutter_matrices", "load_plugin", "parse_effects"]
