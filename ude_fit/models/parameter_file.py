"""The user's own values for the mechanistic model (``--mechanistic-params FILE.toml``).

A TOML file of ``name = number`` pairs, every name a parameter of the system's mechanistic
model (its known geometry, e.g. the aerofoil's ``b``, ``m_T``, or a fitted value, e.g.
``c_h``). Known values replace the design values; fitted ones are taken as given and
left out of the identification. Checked when read: an unknown name, a value that is not a
finite number, or a damping/stiffness at or below zero is a ValueError naming the field.
"""

from __future__ import annotations

import math
import os
import tomllib
from dataclasses import dataclass, field

from .mechanistic import model_class


@dataclass(frozen=True)
class MechanisticParameters:
    """Values from a parameter file: ``known`` (geometry) and ``fitted`` (given instead of
    identified), and the file they came from."""
    path: str
    known: dict = field(default_factory=dict)
    fitted: dict = field(default_factory=dict)

    @classmethod
    def read(cls, path, system: str) -> "MechanisticParameters":
        path = os.fspath(path)
        where = f"--mechanistic-params {path}"
        try:
            with open(path, "rb") as fh:
                doc = tomllib.load(fh)
        except OSError as exc:
            raise ValueError(f"{where}: cannot be read ({exc.strerror})") from None
        except tomllib.TOMLDecodeError as exc:
            raise ValueError(f"{where}: not a TOML file ({' '.join(str(exc).split())})") \
                from None
        return cls.of(path, system, doc)

    @classmethod
    def of(cls, path: str, system: str, values: dict) -> "MechanisticParameters":
        where = f"--mechanistic-params {path}"
        mc = model_class(system)
        known, fitted = {}, {}
        for name, v in values.items():
            if name not in mc.known and name not in mc.fitted:
                raise ValueError(f"{where}: {name!r} is not a parameter of the {system} model "
                                 f"(known: {', '.join(mc.known) or 'none'}; fitted: "
                                 f"{', '.join(mc.fitted)})")
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise ValueError(f"{where}: {name} must be a finite number, not {v!r}")
            if name in mc.must_be_positive and v <= 0:
                raise ValueError(f"{where}: {name} must be positive (a damping or stiffness), "
                                 f"not {v!r}")
            (known if name in mc.known else fitted)[name] = float(v)
        return cls(path, known, fitted)
