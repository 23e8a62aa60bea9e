"""Offline fitting of mechanistic and universal-differential-equation models to limit cycles.

Data flow (one sub-package each): ``data`` (files -> :class:`OrbitDataset`) -> ``models``
(mechanistic, corrections, UDE) -> ``training`` (:class:`FitOptions`, penalties, losses,
:func:`identify`, :func:`train_ude`, :func:`fit_gp`) -> ``analysis`` (continuation,
diagrams, metrics, adequacy) -> :func:`fit` -> ``discovery`` (explain, refine, loop) ->
``report``; :func:`run_pipeline` runs the whole offline job, and ``ude_fit.cli`` is the
command line over it. Models are immutable pytrees (equinox); everything else is
functions over them.

Precision: ude_fit computes in float64 but importing it changes no JAX setting. The
command line switches float64 on; a library user calls
``jax.config.update("jax_enable_x64", True)`` once, before making any array, and the long
jobs (:func:`fit`, :func:`train_ude`, :func:`run_pipeline`) refuse to run without it.
"""

from .analysis import (BifurcationLocation, Branch, BranchErrors, BranchSummary, Equilibria,
                       ModelMetrics, PointError, branch_metrics, diagram_ranges,
                       equilibrium_branch, hopf_point, orbit_at, trace_diagram, trace_flutter,
                       trace_forced)
from .data import (DataError, Orbit, OrbitDataset, estimate_from_data, load,
                   load_campaign, load_lee)
from .fitting import FitResult, StartRecord, fit
from .pipeline import PipelineOptions, PipelineResult, run_pipeline
from .model_file import load_model, save_model
from .models import (UDE, Drive, Duffing7, FlutterQS, MLPCorrection, duffing7,
                     flutter_qs, parameters_of)
from .training import (Diverged, EnergyRising, EnergyShape, EquilibriumPenalty,
                       FitOptions, GPCorrection, RestStability, SmoothnessPenalty,
                       TrainConfig, TrainingData, WeightDecay, fit_gp, identify,
                       residual_forces, train_ude, training_data)

__all__ = [
    "BifurcationLocation", "Branch", "BranchErrors", "BranchSummary", "DataError", "Diverged", "Drive", "Duffing7", "EnergyRising", "EnergyShape",
    "Equilibria", "EquilibriumPenalty", "FitOptions", "FitResult", "FlutterQS",
    "GPCorrection", "MLPCorrection", "ModelMetrics", "Orbit", "OrbitDataset", "PipelineOptions",
    "PipelineResult", "PointError", "RestStability",
    "SmoothnessPenalty", "StartRecord", "TrainConfig", "TrainingData", "UDE", "WeightDecay",
    "branch_metrics", "diagram_ranges", "duffing7", "equilibrium_branch",
    "estimate_from_data", "fit", "fit_gp", "flutter_qs", "hopf_point", "identify", "load",
    "load_campaign", "load_lee", "load_model", "orbit_at", "parameters_of",
    "residual_forces", "run_pipeline", "save_model", "trace_diagram", "trace_flutter", "trace_forced",
    "train_ude", "training_data",
]
