"""The results of comparing a model's diagram with the measured orbits (:mod:`.metrics`
computes them; DESIGN.md defines them): the error at each measured orbit, the branch
figures over those, a Hopf or fold location against its reference, and a model's whole set.

Each is frozen and checks itself when built; the library passes them around and reads them
by attribute. ``to_json`` gives the form metrics.json has always held (same keys, same
values), and only the writers call it."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np


def _figure(name: str, value, *, optional: bool = True) -> None:
    """A figure of merit: a finite number at least 0 (or None where allowed)."""
    if value is None and optional:
        return
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.number)) \
            or not math.isfinite(value) or value < 0:
        raise ValueError(f"{name} must be a finite number at least 0, not {value!r}")


def _number(name: str, value, *, optional: bool = True) -> None:
    if value is None and optional:
        return
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.number)) \
            or not math.isfinite(value):
        raise ValueError(f"{name} must be a finite number, not {value!r}")


def _rms(x: np.ndarray) -> float | None:
    return float(np.sqrt(np.mean(x ** 2))) if x.size else None


@dataclass(frozen=True)
class PointError:
    """One measured orbit against the model: the model's orbit at its parameter with its
    stability (``model`` its amplitude, ``error`` the amplitude error over the largest
    measured amplitude, ``trajectory`` the aligned one-period error), or none (*missed*:
    ``model`` is None). ``model_parameter`` is the fold's parameter when the point was
    compared with the orbit at a model fold next to it."""
    parameter: float
    frequency: float | None
    measured: float
    stable: bool | None
    model: float | None = None
    error: float | None = None
    trajectory: float | None = None
    model_stable: bool | None = None
    model_parameter: float | None = None

    def __post_init__(self):
        _number("parameter", self.parameter, optional=False)
        _figure("measured amplitude", self.measured, optional=False)
        _figure("model amplitude", self.model)
        _figure("error", self.error)
        _figure("trajectory error", self.trajectory)
        _number("model parameter", self.model_parameter)
        if self.model is None:
            extra = [n for n in ("error", "trajectory", "model_stable", "model_parameter")
                     if getattr(self, n) is not None]
            if extra:
                raise ValueError(f"a missed point has no {', '.join(extra)}")
        elif self.error is None:
            raise ValueError("a point the model has an orbit for needs its error")

    @property
    def missed(self) -> bool:
        """The model has no orbit with the measured stability here."""
        return self.model is None

    @property
    def at_fold(self) -> bool:
        return self.model_parameter is not None

    def to_json(self) -> dict:
        out = {"parameter": self.parameter, "frequency": self.frequency,
               "measured": self.measured, "stable": self.stable}
        if self.missed:
            return {**out, "model": None, "error": None, "trajectory": None, "missed": True}
        out.update(model=self.model, error=self.error, trajectory=self.trajectory,
                   missed=False, model_stable=self.model_stable)
        if self.at_fold:
            out.update(at_fold=True, model_parameter=self.model_parameter)
        return out


@dataclass(frozen=True)
class BranchSummary:
    """The branch figures over a set of points: amplitude error RMS and max over the points
    found, the RMS with every missed point counted as if the model predicted rest there
    (error = its measured amplitude: one figure a model cannot improve by dropping hard
    points), the number missed, and the RMS of the trajectory errors. None where no point
    was found."""
    branch_rms: float | None
    branch_rms_with_missed: float | None
    branch_max: float | None
    missed: int
    trajectory_rms: float | None

    def __post_init__(self):
        for name in ("branch_rms", "branch_rms_with_missed", "branch_max", "trajectory_rms"):
            _figure(name, getattr(self, name))
        if isinstance(self.missed, bool) or not isinstance(self.missed, (int, np.integer)) \
                or self.missed < 0:
            raise ValueError(f"missed must be a count at least 0, not {self.missed!r}")
        if (self.branch_rms is None) != (self.branch_max is None):
            raise ValueError("branch_rms and branch_max are both given or both None")
        if self.branch_rms is not None and self.branch_rms > self.branch_max * (1 + 1e-12):
            raise ValueError(f"branch_rms {self.branch_rms!r} exceeds branch_max "
                             f"{self.branch_max!r}")

    @classmethod
    def of(cls, points, a_max: float) -> BranchSummary:
        """The figures over ``points`` (:class:`PointError`), the largest measured amplitude
        ``a_max`` being the scale of the errors."""
        _figure("a_max", a_max, optional=False)
        found = [p for p in points if not p.missed]
        errs = np.array([p.error for p in found], float)
        traj = np.array([p.trajectory for p in found if p.trajectory is not None], float)
        every = np.array([p.measured / a_max if p.missed else p.error for p in points], float)
        return cls(branch_rms=_rms(errs), branch_rms_with_missed=_rms(every),
                   branch_max=float(errs.max()) if errs.size else None,
                   missed=len(points) - len(found), trajectory_rms=_rms(traj))

    def to_json(self) -> dict:
        return {"branch_rms": self.branch_rms,
                "branch_rms_with_missed": self.branch_rms_with_missed,
                "branch_max": self.branch_max, "missed": self.missed,
                "trajectory_rms": self.trajectory_rms}


@dataclass(frozen=True)
class BranchErrors:
    """Every measured orbit against a model's diagram: the points, their summary, and for
    forced data the summary at each forcing frequency (keyed ``f"{f:g}"``)."""
    summary: BranchSummary
    points: tuple[PointError, ...]
    per_frequency: Mapping[str, BranchSummary] | None = None

    def __post_init__(self):
        object.__setattr__(self, "points", tuple(self.points))
        if not all(isinstance(p, PointError) for p in self.points):
            raise ValueError("points must be PointError records")
        if self.summary.missed != sum(p.missed for p in self.points):
            raise ValueError(f"the summary counts {self.summary.missed} missed points, the "
                             f"points {sum(p.missed for p in self.points)}")

    @classmethod
    def of(cls, points, a_max: float, frequencies=None) -> BranchErrors:
        """The errors of ``points``; with ``frequencies`` (forced data), also the summary
        of the points at each (matched to 1e-6 Hz)."""
        points = tuple(points)
        per = None if frequencies is None else {
            f"{f:g}": BranchSummary.of([p for p in points if round(p.frequency, 6) == f], a_max)
            for f in frequencies}
        return cls(BranchSummary.of(points, a_max), points, per)

    def to_json(self) -> dict:
        out = {**self.summary.to_json(), "points": [p.to_json() for p in self.points]}
        if self.per_frequency is not None:
            out["per_frequency"] = {f: s.to_json() for f, s in self.per_frequency.items()}
        return out


@dataclass(frozen=True)
class BifurcationLocation:
    """A Hopf or fold parameter of a model's diagram (None: it has none) against a
    reference value (the truth where known, or an estimate from the measured points;
    ``reference_source`` says which, and is None without a reference)."""
    model: float | None
    reference: float | None = None
    reference_source: str | None = None

    def __post_init__(self):
        _number("model location", self.model)
        _number("reference location", self.reference)
        if (self.reference is None) != (self.reference_source is None):
            raise ValueError("a reference needs its source, and a source its reference")

    @classmethod
    def against(cls, model: float | None, reference: float | None,
                source: str) -> BifurcationLocation:
        return cls(model, reference, None if reference is None else source)

    @property
    def error(self) -> float | None:
        """Model minus reference (None unless both are there)."""
        if self.model is None or self.reference is None:
            return None
        return self.model - self.reference

    def to_json(self) -> dict:
        return {"model": self.model, "reference": self.reference, "error": self.error,
                "reference_source": self.reference_source}


@dataclass(frozen=True)
class ModelMetrics:
    """A model's diagram against the data: the branch errors, the Hopf and (first) fold
    locations, every fold, and for self-excited data the isolas traced through orbits the
    main branch misses and their new folds. ``folds`` is a tuple of parameters, or for
    forced data {frequency key: tuple} (then there are no isola entries)."""
    errors: BranchErrors
    hopf: BifurcationLocation
    fold: BifurcationLocation
    folds: tuple[float, ...] | Mapping[str, tuple[float, ...]]
    isolas: int | None = None
    isola_folds: tuple[float, ...] | None = None

    def __post_init__(self):
        if isinstance(self.folds, Mapping):
            object.__setattr__(self, "folds", {k: tuple(v) for k, v in self.folds.items()})
            if self.isolas is not None or self.isola_folds is not None:
                raise ValueError("forced data has no isola entries")
        else:
            object.__setattr__(self, "folds", tuple(self.folds))
            if self.isolas is None or self.isola_folds is None:
                raise ValueError("self-excited data needs isolas and isola_folds")
            if isinstance(self.isolas, bool) or not isinstance(self.isolas, (int, np.integer)) \
                    or self.isolas < 0:
                raise ValueError(f"isolas must be a count at least 0, not {self.isolas!r}")
            object.__setattr__(self, "isola_folds", tuple(self.isola_folds))

    @classmethod
    def of(cls, errors: BranchErrors, loc: dict, reference: dict, source: str) -> ModelMetrics:
        """From the branch errors and the diagram's locations (:func:`.metrics.locations`),
        with the Hopf/fold ``reference`` ({"hopf": V, "fold": V}, either may be missing)
        that came from ``source``."""
        return cls(errors,
                   *(BifurcationLocation.against(loc.get(k), reference.get(k), source)
                     for k in ("hopf", "fold")),
                   loc["folds"], loc.get("isolas"), loc.get("isola_folds"))

    @property
    def summary(self) -> BranchSummary:
        return self.errors.summary

    @property
    def points(self) -> tuple[PointError, ...]:
        return self.errors.points

    @property
    def per_frequency(self) -> Mapping[str, BranchSummary] | None:
        return self.errors.per_frequency

    @property
    def families(self) -> int:
        """Branch families: one per forcing frequency, or the one self-excited family."""
        return len(self.folds) if isinstance(self.folds, Mapping) else 1

    @property
    def fold_count(self) -> int:
        """Folds in the diagram (every branch, every frequency)."""
        n = sum(len(v) for v in self.folds.values()) if isinstance(self.folds, Mapping) \
            else len(self.folds)
        return n + len(self.isola_folds or ())

    def landmarks(self, spans: Mapping[str | None, tuple[float, float]]) -> dict[str, float]:
        """The diagram's locations outside the measured parameter span of their branch
        family (``spans``: {None: (lo, hi)} for self-excited data, {frequency key: (lo, hi)}
        for forced), where no measured orbit pins them, by name and in the parameter's unit:
        the Hopf point and the first fold of a self-excited diagram, each fold of each
        forcing frequency's branch (in parameter order) of a forced one."""
        outside = lambda family, v: not spans[family][0] <= v <= spans[family][1]
        if isinstance(self.folds, Mapping):
            return {f"fold {i + 1} at {f} Hz": float(v)
                    for f, folds in self.folds.items() for i, v in enumerate(folds)
                    if f in spans and outside(f, v)}
        return {name: float(loc.model) for name, loc in (("Hopf point", self.hopf),
                                                         ("fold", self.fold))
                if loc.model is not None and outside(None, loc.model)}

    def to_json(self) -> dict:
        out = {**self.errors.to_json(), "hopf": self.hopf.to_json(),
               "fold": self.fold.to_json()}
        if isinstance(self.folds, Mapping):
            out["folds"] = {k: list(v) for k, v in self.folds.items()}
        else:
            out.update(folds=list(self.folds), isolas=self.isolas,
                       isola_folds=list(self.isola_folds))
        return out
