"""Undeclared physics: effects a rig can be started with that no register reveals.

Each catalogue effect is one number given at start-up (``--effect NAME=VALUE``).
They are planted so that the fitting side (``ude_fit explain``) can be tested on
data whose generating physics it is not told about. The plugin is the user's own
suspected physics: ``--effect-plugin FILE.py:FUNC`` or ``package.module:FUNC``
with ``FUNC(t, q, qdot, params) -> generalised forces`` (one per physical DoF:
(heave force N, pitch moment N m) for the aerofoil, (force N,) for the
oscillator). The compiled kernel cannot call Python, so a rig with a plugin
samples the plugin force once per internal step (zero-order hold) and runs
slower; the catalogue effects are evaluated inside the integrator's stages.
"""

from __future__ import annotations

import importlib
import importlib.util
import math
from dataclasses import dataclass
from pathlib import Path
from types import MappingProxyType
from typing import Callable

import numpy as np


@dataclass(frozen=True)
class Effect:
    name: str
    slot: int          # index in the kernel's effect vector
    unit: str
    description: str


# Kernel effect vector layout (same slots for both rigs; unused slots stay 0).
EFFECT_SLOTS = 6

FLUTTER_EFFECTS = (
    Effect("freeplay", 0, "rad",
           "pitch freeplay: the linear pitch spring acts on a dead zone of this half-width"),
    Effect("heave_friction", 1, "N",
           "Coulomb friction on heave, F = -mu tanh(h'/1e-3 m/s)"),
    Effect("pitch_friction", 2, "N m",
           "Coulomb friction on pitch, M = -mu tanh(alpha'/1e-2 rad/s)"),
    Effect("heave_cubic", 3, "N/m^3", "cubic heave stiffness, F = -k h^3"),
    Effect("quadratic_damping", 4, "N s^2/m^2", "quadratic heave damping, F = -c |h'| h'"),
    Effect("pitch_quadratic_damping", 5, "N m s^2",
           "quadratic pitch damping, M = -c |alpha'| alpha'"),
)

OSCILLATOR_EFFECTS = (
    Effect("freeplay", 0, "m",
           "dead zone of this half-width in the linear spring of the cantilever"),
    Effect("friction", 1, "N", "Coulomb friction on the tip, F = -mu tanh(x'/1e-3 m/s)"),
    Effect("cubic", 3, "N/m^3", "extra cubic stiffness, F = -k x^3"),
    Effect("quadratic_damping", 4, "N s^2/m^2", "quadratic damping, F = -c |x'| x'"),
)

EFFECTS = {"flutter": FLUTTER_EFFECTS, "oscillator": OSCILLATOR_EFFECTS}


class EffectError(ValueError):
    """A user mistake in an effect or plugin specification (one-line message)."""


def parse_effects(rig: str, specs: list[str] | None) -> tuple[np.ndarray, dict[str, float]]:
    """Turn ``["freeplay=0.01", ...]`` into the kernel's effect vector and a record."""
    catalogue = {e.name: e for e in EFFECTS[rig]}
    vec = np.zeros(EFFECT_SLOTS)
    record: dict[str, float] = {}
    for spec in specs or []:
        name, sep, text = spec.partition("=")
        name = name.strip()
        if not sep:
            raise EffectError(f"--effect {spec!r}: expected NAME=VALUE")
        if name not in catalogue:
            raise EffectError(
                f"--effect {name!r}: unknown effect for the {rig} rig "
                f"(known: {', '.join(catalogue)})")
        try:
            value = float(text)
        except ValueError:
            raise EffectError(f"--effect {name}={text!r}: value is not a number") from None
        if not math.isfinite(value) or value < 0:
            raise EffectError(f"--effect {name}={text}: value must be finite and >= 0")
        if name in record:
            raise EffectError(f"--effect {name} given twice")
        vec[catalogue[name].slot] = value
        record[name] = value
    return vec, record


PluginForce = Callable[[float, np.ndarray, np.ndarray, MappingProxyType], object]


def plugin_source(spec: str) -> tuple[str, str, bool]:
    """(file or module, function name, whether it is a file) of ``FILE.py:FUNC`` or
    ``package.module:FUNC``, checked without running anything; EffectError with one line."""
    target, sep, func_name = spec.rpartition(":")
    if not sep or not target or not func_name:
        raise EffectError(f"--effect-plugin {spec!r}: expected FILE.py:FUNC or module:FUNC")
    is_file = target.endswith(".py") or "/" in target
    if is_file and not Path(target).is_file():
        raise EffectError(f"--effect-plugin: file not found: {target}")
    return target, func_name, is_file


def load_plugin(spec: str) -> PluginForce:
    """Load ``FILE.py:FUNC`` or ``package.module:FUNC``; raise EffectError with one line."""
    target, func_name, is_file = plugin_source(spec)
    if is_file:
        path = Path(target)
        mod_name = f"_rig_plugin_{abs(hash(str(path.resolve())))}"
        module_spec = importlib.util.spec_from_file_location(mod_name, path)
        if module_spec is None or module_spec.loader is None:
            raise EffectError(f"--effect-plugin: cannot load {target} as Python")
        module = importlib.util.module_from_spec(module_spec)
        try:
            module_spec.loader.exec_module(module)
        except Exception as exc:  # the user's file: report, don't crash
            raise EffectError(f"--effect-plugin: {target} failed to import: "
                              f"{type(exc).__name__}: {exc}") from None
    else:
        try:
            module = importlib.import_module(target)
        except Exception as exc:
            raise EffectError(f"--effect-plugin: cannot import module {target!r}: "
                              f"{type(exc).__name__}: {exc}") from None
    func = getattr(module, func_name, None)
    if not callable(func):
        raise EffectError(f"--effect-plugin: {target} has no callable {func_name!r}")
    return func


def check_plugin(func: PluginForce, ndof: int, params: MappingProxyType) -> None:
    """Call the plugin once at rest; it must return ndof finite numbers."""
    try:
        out = np.asarray(func(0.0, np.zeros(ndof), np.zeros(ndof), params), dtype=float)
    except Exception as exc:
        raise EffectError(f"--effect-plugin: the function raised "
                          f"{type(exc).__name__}: {exc}") from None
    if out.shape != (ndof,):
        raise EffectError(f"--effect-plugin: the function must return {ndof} "
                          f"force(s), got shape {out.shape}")
    if not np.all(np.isfinite(out)):
        raise EffectError("--effect-plugin: the function returned a non-finite force at rest")
