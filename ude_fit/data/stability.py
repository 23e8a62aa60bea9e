"""Where a measured orbit's stability comes from: the lab's file-naming conventions, a
campaign file's own ``stable`` attribute, and an explicit user mapping that wins over both.

Naming conventions (one table, :data:`NAME_CONVENTIONS`; the first matching prefix decides):
``CBC_stable_...`` stable, ``CBC_unstable_...`` unstable, ``CBC_v...`` unstable (the lee2020
convention: the unstable points are plain ``CBC_v<airspeed>``). Anything else is unknown.

A point of unknown stability is kept: it still constrains the orbit's shape in the fit, the
stability check of the training and of the adequacy test skips it, and the report and
metrics.json list it by file. Nothing guesses a label.
"""

from __future__ import annotations

import fnmatch
import os
import re
from dataclasses import dataclass, replace

from .orbit import DataError, OrbitDataset

# file-name prefixes and the stability they mean, in the order they are tried
NAME_CONVENTIONS: tuple[tuple[re.Pattern, bool], ...] = (
    (re.compile(r"^CBC_stable_", re.IGNORECASE), True),
    (re.compile(r"^CBC_unstable_", re.IGNORECASE), False),
    (re.compile(r"^CBC_v", re.IGNORECASE), False),
)
_WORDS = {"stable": True, "unstable": False}


def stability_from_name(name: str) -> bool | None:
    """The stability a file's base name states by the lab's conventions, None if none."""
    base = os.path.basename(name)
    for pattern, stable in NAME_CONVENTIONS:
        if pattern.match(base):
            return stable
    return None


def _names(source: str) -> tuple[str, ...]:
    """What a rule's pattern is matched against: the file's base name and, for a point of a
    campaign file (``path#key``), also ``name#key``."""
    path, sep, key = source.partition("#")
    base = os.path.basename(path)
    return (base, f"{base}#{key}") if sep else (base,)


@dataclass(frozen=True)
class StabilityRule:
    """Points whose file name matches ``pattern`` (shell-style glob) are ``stable``."""
    pattern: str
    stable: bool

    def __post_init__(self):
        if not isinstance(self.pattern, str) or not self.pattern.strip():
            raise ValueError("--stability: empty file pattern")
        if not isinstance(self.stable, bool):
            raise ValueError(f"--stability {self.pattern}: stable must be True or False")

    def matches(self, source: str) -> bool:
        return any(fnmatch.fnmatchcase(n, self.pattern) for n in _names(source))

    def spec(self) -> str:
        return f"{self.pattern}={'stable' if self.stable else 'unstable'}"


@dataclass(frozen=True)
class StabilityLabels:
    """The user's explicit stability mapping (``--stability GLOB=stable|unstable``, each
    flag may hold several rules separated by commas). It wins over the file names and the
    campaign attributes. A rule that matches no point, or a point two rules give opposite
    labels, is an error (a typo must not silently leave labels as they were)."""
    rules: tuple[StabilityRule, ...] = ()

    def __post_init__(self):
        object.__setattr__(self, "rules", tuple(self.rules))
        for r in self.rules:
            if not isinstance(r, StabilityRule):
                raise ValueError(f"--stability: rules must be StabilityRule objects, not {r!r}")

    @classmethod
    def parse(cls, specs) -> "StabilityLabels":
        """From ``["CBC_a*=stable,CBC_b*=unstable", ...]``; ValueError (one line) naming the
        bad rule."""
        rules = []
        for spec in specs or ():
            for part in str(spec).split(","):
                pattern, sep, word = part.strip().rpartition("=")
                if not sep or not pattern.strip():
                    raise ValueError(f"--stability {part.strip()!r}: expected GLOB=stable or "
                                     "GLOB=unstable")
                if word.strip().lower() not in _WORDS:
                    raise ValueError(f"--stability {part.strip()!r}: the label must be stable "
                                     f"or unstable, not {word.strip()!r}")
                rules.append(StabilityRule(pattern.strip(), _WORDS[word.strip().lower()]))
        return cls(tuple(rules))

    def apply(self, ds: OrbitDataset) -> OrbitDataset:
        """``ds`` with every point a rule matches relabelled (and its label's origin saying
        which rule); DataError for a rule that matches nothing or conflicting rules."""
        if not self.rules:
            return ds
        used = set()
        orbits = []
        for o in ds.orbits:
            hits = [r for r in self.rules if r.matches(o.source)]
            used.update(r.spec() for r in hits)
            if len({r.stable for r in hits}) > 1:
                raise DataError(f"{o.source}: --stability rules disagree ("
                                + ", ".join(r.spec() for r in hits) + ")")
            if hits:
                o = replace(o, stable=hits[0].stable,
                            stability_from=f"--stability {hits[0].spec()}")
            orbits.append(o)
        for r in self.rules:
            if r.spec() not in used:
                raise DataError(f"--stability {r.spec()}: matches no loaded point")
        return OrbitDataset(ds.system, tuple(orbits), ds.sources)

    def to_json(self) -> list:
        return [r.spec() for r in self.rules]
