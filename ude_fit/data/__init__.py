"""Measured periodic orbits: :class:`Orbit`, :class:`OrbitDataset`, and the readers of
campaign HDF5 files and lee2020 wind-tunnel files (:func:`load` takes any mix)."""

from .campaign import load_campaign
from .estimates import estimate_from_data
from .lee import load_lee
from .load import load
from .orbit import DataError, Orbit, OrbitDataset
from .stability import StabilityLabels, StabilityRule, stability_from_name

__all__ = ["DataError", "Orbit", "OrbitDataset", "estimate_from_data", "load",
           "load_campaign", "load_lee", "StabilityLabels", "StabilityRule",
           "stability_from_name"]
