"""The two kinds of rig the data can come from, as facts in one table.

The data, analysis and report layers sit below (or beside) the mechanistic model classes, so
they cannot ask a model what kind of system it describes; they look the kind up here by the
name the data carries ("flutter" or "oscillator"). The distinction that drives the numerics is
physical: an *autonomous* system (the aerofoil) has an equilibrium that loses stability at a
Hopf point, with limit cycles whose frequency is an output; a *forced* one (the shaker-driven
oscillator) has periodic responses at an imposed frequency, grouped into one S-curve per
frequency.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class SystemKind:
    name: str                       # as in the data files and on the command line
    title: str                      # for reports
    coordinates: tuple[str, ...]    # the measured coordinates, in the data's order
    parameter: str                  # the bifurcation parameter's name in the data
    parameter_label: str            # ... as a report states it
    parameter_unit: str
    diagram_axis: str               # the horizontal axis of a diagram or residual figure
    autonomous: bool                # limit cycles of an autonomous system (Hopf, folds in V)
    # the diagram is traced up to this many times the largest measured amplitude (of each
    # forcing frequency's, for a forced system)
    amplitude_window: float
    # the coordinates that are angles (a sensor reads them modulo 2 pi)
    angles: tuple[str, ...] = ()

    @property
    def forced(self) -> bool:
        return not self.autonomous


AEROFOIL = SystemKind("flutter", "aerofoil (flutter)", ("h", "alpha"), "airspeed", "airspeed",
                      "m/s", "airspeed (m/s)", autonomous=True, amplitude_window=1.4,
                      angles=("alpha",))
OSCILLATOR = SystemKind("oscillator", "forced oscillator", ("x",), "forcing_amplitude",
                        "forcing amplitude", "m/s²", "forcing frequency (Hz)", autonomous=False,
                        amplitude_window=1.5)
KINDS = {k.name: k for k in (AEROFOIL, OSCILLATOR)}


@dataclass(frozen=True)
class AirspeedWindow:
    """Where an aerofoil's diagram is traced, from the measured airspeeds: their span (a
    tenth of the largest where they nearly coincide) and the window from 1.5 spans below the
    lowest (at least 0.5 m/s) to 0.75 of a span above the highest, wide enough for a fold
    below the measured orbits and a Hopf point above them."""
    span: float
    low: float
    high: float

    @classmethod
    def of(cls, airspeeds) -> "AirspeedWindow":
        V = np.asarray(airspeeds, float)
        span = max(float(np.ptp(V)), 0.1 * float(V.max()))
        return cls(span, max(0.5, float(V.min()) - 1.5 * span), float(V.max()) + 0.75 * span)


def system_kind(name: str) -> SystemKind:
    """The kind named ``name``; a ValueError naming the known ones otherwise."""
    try:
        return KINDS[name]
    except KeyError:
        raise ValueError(f"system must be one of {', '.join(map(repr, KINDS))}, "
                         f"not {name!r}") from None
