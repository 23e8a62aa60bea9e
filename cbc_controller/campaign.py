"""Campaign files (TOML): parse and validate before anything touches a rig.

Every error names the field: ``campaign.toml: parameter.values[2] = 45: outside
0..40 m/s (airspeed)``. Ranges of rig settings come from the register map, the
rig's datasheet, so a campaign cannot ask for what the device would refuse.
"""

from __future__ import annotations

import math
import tomllib
from pathlib import Path

from rig_sim.device import register_map as M

from .plans.options import OPTIONS, typed


class CampaignError(ValueError):
    """A malformed campaign file (one line, naming the field)."""


_TOP = {"campaign", "rig", "loop", "parameter", "frequencies", "cbc"}
_CAMPAIGN = {"name": str, "rig": str, "seed": int, "description": str}
_RIG = {"time_scale": float, "lockstep": bool, "noise": float, "effects": list, "plugin": str,
        "seed": int}
_LOOP = {"rate_hz": float, "lockstep_slice_s": float, "reconnect_s": float, "watchdog_s": float,
         "max_settle_rig_s": float}


def load_campaign(path: str | Path) -> tuple[dict, str]:
    """Read and validate a campaign file; returns (config, raw text)."""
    path = Path(path)
    name = path.name
    try:
        text = path.read_text()
    except OSError as exc:
        raise CampaignError(f"{path}: cannot read ({exc.strerror})") from None
    try:
        raw = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise CampaignError(f"{name}: not valid TOML ({exc})") from None
    return validate(raw, name), text


def _type(name: str, field: str, value, kind) -> object:
    try:
        return typed(field, value, kind)
    except ValueError as exc:
        raise CampaignError(f"{name}: {exc}") from None


def _section(name: str, raw: dict, key: str, schema: dict) -> dict:
    sec = raw.get(key, {})
    if not isinstance(sec, dict):
        raise CampaignError(f"{name}: [{key}] must be a table")
    out = {}
    for k, v in sec.items():
        if k not in schema:
            raise CampaignError(f"{name}: {key}.{k}: unknown field (known: {', '.join(schema)})")
        out[k] = _type(name, f"{key}.{k}", v, schema[k])
    return out


def _values(name: str, raw: dict, key: str) -> list[float]:
    sec = raw.get(key)
    if not isinstance(sec, dict):
        raise CampaignError(f"{name}: [{key}] is missing")
    unknown = set(sec) - {"values", "start", "stop", "step"}
    if unknown:
        raise CampaignError(f"{name}: {key}.{sorted(unknown)[0]}: unknown field")
    if "values" in sec:
        vals = sec["values"]
        if not isinstance(vals, list) or not vals:
            raise CampaignError(f"{name}: {key}.values must be a non-empty list of numbers")
        return [_type(name, f"{key}.values[{i}]", v, float) for i, v in enumerate(vals)]
    try:
        start, stop, step = (_type(name, f"{key}.{k}", sec[k], float) for k in ("start", "stop", "step"))
    except KeyError as exc:
        raise CampaignError(f"{name}: {key}.{exc.args[0]} is missing (or give {key}.values)") from None
    if step <= 0 or stop < start:
        raise CampaignError(f"{name}: {key}: need step > 0 and stop >= start")
    n = int(math.floor((stop - start) / step + 1e-9)) + 1
    if n > 1000:
        raise CampaignError(f"{name}: {key}: {n} values is too many (at most 1000)")
    return [start + i * step for i in range(n)]


def _in_range(name: str, field: str, value: float, register: str, rig: str) -> None:
    reg = M.BY_NAME[register]
    lo, hi = reg.range_for(rig)
    if not lo <= value <= hi:
        raise CampaignError(f"{name}: {field} = {value:g}: outside {lo:g}..{hi:g} {reg.unit} ({register})")


def _check_embedded_rig(name: str, rig: str, section: dict) -> None:
    """[rig] describes the embedded rig, which is `rig-sim serve` itself: its effects and
    plugin are checked against rig_sim's own catalogue now, not when it starts. (The
    controller imports nothing else of rig_sim but the register map.)"""
    from rig_sim.physics.effects import EffectError, parse_effects, plugin_source

    effects = section.get("effects", [])
    for i, spec in enumerate(effects):
        if not isinstance(spec, str):
            raise CampaignError(f'{name}: rig.effects[{i}] = {spec!r}: expected "NAME=VALUE"')
        try:
            parse_effects(rig, [spec])
        except EffectError as exc:      # its message names the CLI option: keep the reason
            raise CampaignError(f"{name}: rig.effects[{i}] = {spec!r}: "
                                f"{str(exc).split(': ', 1)[-1]}") from None
    try:
        parse_effects(rig, effects)     # together: an effect given twice
    except EffectError as exc:
        raise CampaignError(f"{name}: rig.effects: {str(exc).removeprefix('--effect ')}") from None
    if "plugin" in section:
        try:
            plugin_source(section["plugin"])
        except EffectError as exc:
            raise CampaignError(f"{name}: rig.plugin = {section['plugin']!r}: "
                                f"{str(exc).split(': ', 1)[-1]}") from None


def validate(raw: dict, name: str = "campaign") -> dict:
    for k in raw:
        if k not in _TOP:
            raise CampaignError(f"{name}: [{k}]: unknown section (known: {', '.join(sorted(_TOP))})")
    camp = _section(name, raw, "campaign", _CAMPAIGN)
    rig = camp.get("rig")
    if rig not in ("flutter", "oscillator"):
        raise CampaignError(f"{name}: campaign.rig = {rig!r}: must be \"flutter\" or \"oscillator\"")
    cfg = {"campaign": camp, "rig": _section(name, raw, "rig", _RIG),
           "loop": _section(name, raw, "loop", _LOOP)}
    if cfg["rig"].get("time_scale") is not None and cfg["rig"]["time_scale"] <= 0:
        raise CampaignError(f"{name}: rig.time_scale must be > 0")
    if cfg["rig"].get("noise", 0.0) < 0:
        raise CampaignError(f"{name}: rig.noise must be >= 0")
    _check_embedded_rig(name, rig, cfg["rig"])
    for k in ("rate_hz", "lockstep_slice_s", "reconnect_s", "watchdog_s", "max_settle_rig_s"):
        if k in cfg["loop"] and cfg["loop"][k] <= 0:
            raise CampaignError(f"{name}: loop.{k} must be > 0")
    if "rate_hz" in cfg["loop"] and not 1 <= cfg["loop"]["rate_hz"] <= 2000:
        raise CampaignError(f"{name}: loop.rate_hz = {cfg['loop']['rate_hz']:g}: outside 1..2000 Hz")
    if "watchdog_s" in cfg["loop"]:
        _in_range(name, "loop.watchdog_s", cfg["loop"]["watchdog_s"], "watchdog_timeout", rig)

    cbc = raw.get("cbc", {})
    if not isinstance(cbc, dict):
        raise CampaignError(f"{name}: [cbc] must be a table")
    try:
        OPTIONS[rig].from_table(cbc)      # the plan's typed options check every field
    except ValueError as exc:
        raise CampaignError(f"{name}: {exc}") from None
    cfg["cbc"] = dict(cbc)

    if rig == "flutter":
        values = _values(name, raw, "parameter")
        for i, v in enumerate(values):
            _in_range(name, f"parameter.values[{i}]", v, "airspeed", rig)
        cfg["parameter"] = {"name": "airspeed", "values": values}
        if "frequencies" in raw:
            raise CampaignError(f"{name}: [frequencies] is for the oscillator; the flutter rig "
                                "uses [parameter] (airspeeds)")
    else:
        freqs = _values(name, raw, "frequencies")
        for i, v in enumerate(freqs):
            _in_range(name, f"frequencies.values[{i}]", v, "frequency", rig)
        cfg["frequencies"] = freqs
        if "parameter" in raw:
            raise CampaignError(f"{name}: [parameter] is for the flutter rig; the oscillator "
                                "sweeps the target amplitude at each of [frequencies]")
    return cfg
