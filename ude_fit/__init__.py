"""Offline fitting of mechanistic and universal-differential-equation models to limit cycles.

Data flow: files -> :class:`OrbitDataset` -> :func:`identify` (mechanistic) -> UDE starts
(:func:`train_ude` or :func:`fit_gp`) -> continuation (:func:`trace_flutter`,
:func:`trace_forced`) -> metrics -> report. :func:`fit` runs the whole chain.
Models are immutable pytrees (equinox); everything else is functions over them.
"""
import jax as _jax

# Fitting and continuation need float64; ude_fit switches JAX to it on import.
_jax.config.update("jax_enable_x64", True)

from ._continuation import (Branch, Equilibria, equilibrium_branch, hopf_point,  # noqa: E402
                            orbit_at, trace_flutter, trace_forced)
from ._data import (DataError, Orbit, OrbitDataset, load, load_campaign,  # noqa: E402
                    load_lee)
from ._fit import (FitOptions, FitResult, diagram_ranges, fit, trace_diagram)  # noqa: E402
from ._gp import GPCorrection, fit_gp  # noqa: E402
from ._identify import TrainingData, identify, residual_forces, training_data  # noqa: E402
from ._io import load_model, save_model  # noqa: E402
from ._metrics import branch_metrics, estimate_from_data  # noqa: E402
from ._models import (UDE, Drive, Duffing7, FlutterQS, MLPCorrection, duffing7,  # noqa: E402
                      flutter_qs, parameters_of)
from ._train import Diverged, TrainConfig, train_ude  # noqa: E402

__all__ = [
    "Branch", "DataError", "Diverged", "Drive", "Duffing7", "Equilibria", "FitOptions",
    "FitResult", "FlutterQS", "GPCorrection", "MLPCorrection", "Orbit", "OrbitDataset",
    "TrainConfig", "TrainingData", "UDE", "branch_metrics", "diagram_ranges", "duffing7",
    "equilibrium_branch", "estimate_from_data", "fit", "fit_gp", "flutter_qs", "hopf_point",
    "identify", "load", "load_campaign", "load_lee", "load_model", "orbit_at",
    "parameters_of", "residual_forces", "save_model", "trace_diagram", "trace_flutter",
    "trace_forced", "train_ude", "training_data",
]
