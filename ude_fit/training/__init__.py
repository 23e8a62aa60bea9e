"""Training: the typed options of a fit, the penalties, the losses, the optimiser, the
mechanistic identification (least squares) and the Gaussian-process correction."""

from .gp import GPCorrection, fit_gp
from .identify import TrainingData, identify, residual_forces, training_data
from .optimise import Diverged, minimize
from .options import FitOptions, TrainConfig
from .penalties import (PENALTIES, EnergyRising, EnergyShape, EquilibriumPenalty, Penalty,
                        RestStability, SmoothnessPenalty, WeightDecay)
from .train import refine_mechanistic, train_ensemble, train_ude

__all__ = ["PENALTIES", "Diverged", "EnergyRising", "EnergyShape", "EquilibriumPenalty",
           "FitOptions", "GPCorrection", "Penalty", "RestStability", "SmoothnessPenalty",
           "TrainConfig", "TrainingData", "WeightDecay", "fit_gp", "identify", "minimize",
           "refine_mechanistic", "residual_forces", "train_ensemble", "train_ude",
           "training_data"]
