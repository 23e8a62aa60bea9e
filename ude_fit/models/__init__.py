"""Models as immutable pytrees: the mechanistic models, a refined model with named effects
added, the corrections (neural networks), the UDE, and the integrators over them."""

from .corrections import MLPCorrection, PolynomialParamCorrection, Scaling
from .mechanistic import Drive, Duffing7, FlutterQS, duffing7, flutter_qs, parameters_of
from .refined import Refined
from .ude import UDE

__all__ = ["Drive", "Duffing7", "FlutterQS", "MLPCorrection", "PolynomialParamCorrection",
           "Refined", "Scaling", "UDE", "duffing7", "flutter_qs", "parameters_of"]
