"""Another configuration of a rig: named physical parameters in place of the design values
(``rig-sim serve --physics NAME=VALUE``), e.g. ``c1=0 c3=0`` for an aerofoil whose
aerodynamic lag state no longer acts on it (quasi-steady aerodynamics). Unlike the
catalogue effects, these change the rig's own model; the rig's registers reveal neither."""

from __future__ import annotations

import math
from dataclasses import fields, replace

from .flutter import FlutterParams
from .oscillator import OscillatorParams

DESIGN = {"flutter": FlutterParams, "oscillator": OscillatorParams}


class ConfigurationError(ValueError):
    """A user mistake in a --physics specification (one-line message)."""


def configured_params(rig: str, specs: list[str] | tuple = ()):
    """The ``rig``'s physical parameters: its design values with ``["NAME=VALUE", ...]``
    in their place."""
    design = DESIGN[rig]()
    names = [f.name for f in fields(design)]
    given: dict[str, float] = {}
    for spec in specs or ():
        name, sep, text = spec.partition("=")
        name = name.strip()
        if not sep:
            raise ConfigurationError(f"--physics {spec!r}: expected NAME=VALUE")
        if name not in names:
            raise ConfigurationError(f"--physics {name!r}: not a parameter of the {rig} rig "
                                     f"(its parameters: {', '.join(names)})")
        try:
            value = float(text)
        except ValueError:
            raise ConfigurationError(f"--physics {name}={text!r}: value is not a number") from None
        if not math.isfinite(value):
            raise ConfigurationError(f"--physics {name}={text}: value must be finite")
        if name in given:
            raise ConfigurationError(f"--physics {name} given twice")
        given[name] = value
    return replace(design, **given)
