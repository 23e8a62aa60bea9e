"""Fleet files (TOML): a grid of campaign files x rig settings x seeds, checked before anything
starts. Every error is one line naming the field: ``fleet.toml: settings[1].effects.spin:
unknown effect for the flutter rig (known: freeplay, ...)``.

The rig settings are those of ``rig-sim serve`` that the campaign's embedded rig takes (its
``[rig]`` table, see :mod:`cbc_controller.campaign`): ``noise``, ``effects``, ``plugin`` and,
from the grid's ``seeds``, ``seed``. Each member gets its own campaign file: the campaign's
text with its ``[rig]`` table set to the member's settings.
"""

from __future__ import annotations

import math
import re
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

from rig_sim.physics.effects import EffectError, parse_effects

from ..campaign import CampaignError, load_campaign, validate
from ._toml import dump_toml


class FleetError(ValueError):
    """A malformed fleet file (one line, naming the field)."""


_FLEET_FIELDS = {"name", "campaigns", "seeds", "clock", "time_scale", "retries",
                 "cpus_per_member"}
_SETTINGS_FIELDS = {"label", "rig", "noise", "effects", "plugin"}
_CLOCKS = ("lockstep", "time-scale")
_LABEL = re.compile(r"^[A-Za-z0-9_.-]+$")
PLUGIN_FILE = "plugin.py"          # a member's plugin, beside its campaign file


@dataclass(frozen=True)
class RigSettings:
    """One point on the fleet's rig-settings axis (``rig-sim serve`` options)."""
    label: str
    rig: str | None = None                          # only for this rig's campaigns
    noise: float | None = None                      # None: the campaign's own
    effects: tuple[tuple[str, float], ...] = ()     # undeclared physics, name -> value
    plugin: str | None = None                       # FILE.py:FUNC, FILE absolute

    def applies_to(self, rig: str) -> bool:
        return self.rig is None or self.rig == rig

    def record(self) -> dict:
        return {"label": self.label, "noise": self.noise, "effects": dict(self.effects),
                "plugin": self.plugin}


@dataclass(frozen=True)
class Member:
    """One campaign of the fleet: what a task needs to run it anywhere (no shared files)."""
    id: str
    campaign: str                # the source campaign file
    rig: str                     # "flutter" or "oscillator"
    settings: RigSettings
    seed: int | None             # None: the campaign's own
    campaign_toml: str           # the member's own campaign file
    plugin_source: bytes | None = field(default=None, repr=False)
    clock_args: tuple[str, ...] = ()      # --lockstep or --time-scale K

    def record(self) -> dict:
        return {"member": self.id, "campaign": self.campaign, "rig": self.rig,
                "settings": {**self.settings.record(), "seed": self.seed,
                             "clock": " ".join(self.clock_args) or "campaign's own"}}


@dataclass(frozen=True)
class FleetOptions:
    path: str
    name: str
    text: str                              # the fleet file, recorded in the index
    campaigns: tuple[str, ...]
    settings: tuple[RigSettings, ...]
    seeds: tuple[int | None, ...]
    clock: str | None = None               # None: each campaign's own [rig] clock
    time_scale: float | None = None
    retries: int = 3                       # Ray task retries when a worker or node dies
    cpus_per_member: float = 1.0           # the controller and its rig: about one core

    def __post_init__(self):
        if not self.campaigns:
            raise FleetError(f"{self.path}: fleet.campaigns: empty grid (give at least one "
                             "campaign file)")
        if not self.seeds:
            raise FleetError(f"{self.path}: fleet.seeds: empty grid (give at least one seed, "
                             "or leave it out for each campaign's own)")
        if not self.settings:
            raise FleetError(f"{self.path}: settings: empty grid")
        if self.clock is not None and self.clock not in _CLOCKS:
            raise FleetError(f"{self.path}: fleet.clock = {self.clock!r}: must be one of "
                             + ", ".join(f'"{c}"' for c in _CLOCKS))
        if (self.clock == "time-scale") != (self.time_scale is not None):
            raise FleetError(f"{self.path}: fleet.time_scale: give it with clock = "
                             "\"time-scale\" (and only then)")
        if self.time_scale is not None and not self.time_scale > 0:
            raise FleetError(f"{self.path}: fleet.time_scale must be > 0")
        if self.retries < 0:
            raise FleetError(f"{self.path}: fleet.retries must be >= 0")
        if not self.cpus_per_member > 0:
            raise FleetError(f"{self.path}: fleet.cpus_per_member must be > 0")

    def clock_args(self) -> tuple[str, ...]:
        if self.clock == "lockstep":
            return ("--lockstep",)
        if self.clock == "time-scale":
            return ("--time-scale", repr(self.time_scale))
        return ()

    def members(self) -> list[Member]:
        """The grid, campaign-major: campaign x settings (those for its rig) x seed."""
        out = []
        for campaign in self.campaigns:
            config, text = load_campaign(campaign)
            raw = tomllib.loads(text)
            rig = config["campaign"]["rig"]
            for settings in self.settings:
                if not settings.applies_to(rig):
                    continue
                for seed in self.seeds:
                    out.append(self._member(campaign, raw, rig, settings, seed))
        return out

    def _member(self, campaign: str, raw: dict, rig: str, settings: RigSettings,
                seed: int | None) -> Member:
        ident = f"{Path(campaign).stem}-{settings.label}" + ("" if seed is None else f"-s{seed}")
        raw = {k: dict(v) if isinstance(v, dict) else v for k, v in raw.items()}
        raw["campaign"]["name"] = ident
        table = raw.setdefault("rig", {})
        if seed is not None:
            table["seed"] = seed
        if settings.noise is not None:
            table["noise"] = settings.noise
        if settings.effects:
            table["effects"] = [f"{k}={v!r}" for k, v in settings.effects]
        source = None
        if settings.plugin is not None:
            file, _, func = settings.plugin.rpartition(":")
            source = Path(file).read_bytes()
            table["plugin"] = f"{PLUGIN_FILE}:{func}"
        text = (f"# fleet {self.name}: member {ident} ({campaign}, settings "
                f"{settings.label!r}, seed {seed})\n" + dump_toml(raw))
        check = tomllib.loads(text)                 # the member's file is a valid campaign,
        if settings.plugin is not None:             # its plugin where it is on this machine
            check["rig"]["plugin"] = settings.plugin
        validate(check, ident)
        return Member(ident, campaign, rig, settings, seed, text, source, self.clock_args())


# ------------------------------------------------------------------ parsing -------------
def _number(where: str, value, kind=float):
    ok = isinstance(value, int) if kind is int else isinstance(value, (int, float))
    if isinstance(value, bool) or not ok or (kind is float and not math.isfinite(value)):
        raise FleetError(f"{where} = {value!r}: expected {'an integer' if kind is int else 'a finite number'}")
    return kind(value)


def _string(where: str, value) -> str:
    if not isinstance(value, str):
        raise FleetError(f"{where} = {value!r}: expected a string")
    return value


def _settings(name: str, i: int, raw, rigs: set[str], base: Path) -> RigSettings:
    where = f"{name}: settings[{i}]"
    if not isinstance(raw, dict):
        raise FleetError(f"{where}: must be a table ([[settings]])")
    for k in raw:
        if k not in _SETTINGS_FIELDS:
            raise FleetError(f"{where}.{k}: unknown field (known: {', '.join(sorted(_SETTINGS_FIELDS))})")
    label = raw.get("label", f"settings{i}")
    if not isinstance(label, str) or not _LABEL.match(label):
        raise FleetError(f"{where}.label = {label!r}: letters, digits, '_', '.', '-' only")
    rig = raw.get("rig")
    if rig is not None and rig not in rigs:
        raise FleetError(f"{where}.rig = {rig!r}: no campaign of the fleet is for this rig "
                         f"(they are for: {', '.join(sorted(rigs))})")
    noise = None
    if "noise" in raw:
        noise = _number(f"{where}.noise", raw["noise"])
        if noise < 0:
            raise FleetError(f"{where}.noise = {noise:g}: must be >= 0")
    effects = raw.get("effects", {})
    if not isinstance(effects, dict):
        raise FleetError(f"{where}.effects: must be a table, e.g. {{ freeplay = 0.01 }}")
    pairs = tuple((str(k), _number(f"{where}.effects.{k}", v)) for k, v in effects.items())
    for r in ([rig] if rig else sorted(rigs)):
        for k, v in pairs:
            try:
                parse_effects(r, [f"{k}={v!r}"])
            except EffectError as exc:
                raise FleetError(f"{where}.effects.{k}: {str(exc).split(': ', 1)[-1]}"
                                 + ("" if rig else " (set settings.rig to limit it to one rig)")) from None
    plugin = raw.get("plugin")
    if plugin is not None:
        file, sep, func = plugin.rpartition(":") if isinstance(plugin, str) else ("", "", "")
        if not sep or not file.endswith(".py") or not func.isidentifier():
            raise FleetError(f"{where}.plugin = {plugin!r}: expected FILE.py:FUNC")
        path = (base / file).resolve()
        if not path.is_file():
            raise FleetError(f"{where}.plugin: file not found: {path}")
        plugin = f"{path}:{func}"
    return RigSettings(label, rig, noise, pairs, plugin)


def parse_fleet(raw: dict, path: str, text: str = "") -> FleetOptions:
    """The fleet options from a parsed fleet file (paths relative to the file)."""
    name = Path(path).name
    base = Path(path).resolve().parent
    for k in raw:
        if k not in ("fleet", "settings"):
            raise FleetError(f"{name}: [{k}]: unknown section (known: fleet, settings)")
    fleet = raw.get("fleet")
    if not isinstance(fleet, dict):
        raise FleetError(f"{name}: [fleet] is missing")
    for k in fleet:
        if k not in _FLEET_FIELDS:
            raise FleetError(f"{name}: fleet.{k}: unknown field (known: {', '.join(sorted(_FLEET_FIELDS))})")
    campaigns = fleet.get("campaigns")
    if not isinstance(campaigns, list) or not all(isinstance(c, str) for c in campaigns):
        raise FleetError(f"{name}: fleet.campaigns: expected a list of campaign files")
    files, rigs, stems = [], set(), set()
    for i, c in enumerate(campaigns):
        p = (base / c).resolve()
        try:
            config, _ = load_campaign(p)
        except CampaignError as exc:
            raise FleetError(f"{name}: fleet.campaigns[{i}]: {exc}") from None
        if p.stem in stems:
            raise FleetError(f"{name}: fleet.campaigns[{i}]: a second campaign named {p.stem!r}")
        stems.add(p.stem)
        files.append(str(p))
        rigs.add(config["campaign"]["rig"])
    seeds = fleet.get("seeds")
    if seeds is not None and not isinstance(seeds, list):
        raise FleetError(f"{name}: fleet.seeds: expected a list of integers")
    seeds = (None,) if seeds is None else tuple(_number(f"{name}: fleet.seeds[{i}]", s, int)
                                                for i, s in enumerate(seeds))
    if len(set(seeds)) != len(seeds):
        raise FleetError(f"{name}: fleet.seeds: a seed given twice")
    settings_raw = raw.get("settings", [{"label": "default"}])
    if not isinstance(settings_raw, list):
        raise FleetError(f"{name}: settings: expected [[settings]] tables")
    settings = tuple(_settings(name, i, s, rigs, base) for i, s in enumerate(settings_raw))
    labels = [s.label for s in settings]
    if len(set(labels)) != len(labels):
        raise FleetError(f"{name}: settings: a label given twice")
    time_scale = fleet.get("time_scale")
    return FleetOptions(
        path=name, name=_string(f"{name}: fleet.name", fleet.get("name", Path(path).stem)),
        text=text,
        campaigns=tuple(files), settings=settings, seeds=seeds,
        clock=None if "clock" not in fleet else _string(f"{name}: fleet.clock", fleet["clock"]),
        time_scale=None if time_scale is None else _number(f"{name}: fleet.time_scale", time_scale),
        retries=_number(f"{name}: fleet.retries", fleet.get("retries", 3), int),
        cpus_per_member=_number(f"{name}: fleet.cpus_per_member", fleet.get("cpus_per_member", 1.0)))


def load_fleet(path: str | Path) -> FleetOptions:
    """Read and check a fleet file; raises FleetError (one line) on any mistake."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise FleetError(f"{path}: cannot read ({exc.strerror})") from None
    try:
        raw = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise FleetError(f"{path.name}: not valid TOML ({exc})") from None
    options = parse_fleet(raw, str(path), text)
    try:
        options.members()        # every member's campaign file is checked here, not on a node
    except CampaignError as exc:
        raise FleetError(f"{path.name}: {exc}") from None
    return options
