"""A model's bifurcation diagram as one typed object: its branches, keyed as the model
files and metrics.json have always keyed them, and the questions every reader asks of it
(which branch starts at the Hopf point, which are isolas, which holds a given forcing
frequency) answered here only.

Keys: the aerofoil's branch from the Hopf point is ``"flutter"``, each isola traced
through a measured orbit ``"flutter/<i>"``; a forced system has one branch per forcing
frequency, keyed by the frequency in Hz (a float; its string in JSON)."""

from __future__ import annotations

from collections.abc import Iterator, Mapping

from .continuation import Branch

MAIN = "flutter"


def _same_frequency(f: float, g: float) -> bool:
    return abs(float(f) - float(g)) <= 1e-6 * max(1.0, float(g))


class Diagram(Mapping):
    """Branches by key (a read-only mapping); see the module docstring for the keys."""

    def __init__(self, branches: Mapping | None = None):
        self._branches = dict(branches or {})

    @classmethod
    def of(cls, diagram) -> "Diagram":
        """``diagram`` as a Diagram (a plain {key: Branch} mapping is wrapped)."""
        return diagram if isinstance(diagram, Diagram) else cls(diagram)

    def __getitem__(self, key):
        return self._branches[key]

    def __iter__(self) -> Iterator:
        return iter(self._branches)

    def __len__(self) -> int:
        return len(self._branches)

    def __repr__(self) -> str:
        return f"Diagram({list(self._branches)!r})"

    @property
    def autonomous(self) -> bool:
        """An aerofoil's diagram (branches in the airspeed) rather than a forced one."""
        return any(str(k).startswith(MAIN) for k in self._branches)

    @property
    def main(self) -> Branch | None:
        """The aerofoil's branch from the Hopf point (None for a forced system)."""
        return self._branches.get(MAIN)

    @property
    def isolas(self) -> list[Branch]:
        """The aerofoil's branches not from the Hopf point, in the order found."""
        return [b for k, b in self._branches.items()
                if str(k).startswith(MAIN) and k != MAIN]

    def with_isola(self, branch: Branch) -> "Diagram":
        return Diagram({**self._branches, f"{MAIN}/{len(self._branches)}": branch})

    def frequencies(self) -> list[float]:
        """A forced system's forcing frequencies (Hz), in the order traced."""
        return [] if self.autonomous else [float(f) for f in self._branches]

    def at_frequency(self, freq: float) -> Branch | None:
        return next((b for f, b in self._branches.items()
                     if not self.autonomous and _same_frequency(f, freq)), None)

    def branch_for(self, freq: float | None) -> Branch | None:
        """The branch a figure draws: the aerofoil's main one, or the one at ``freq``."""
        if self.autonomous:
            return self.main
        return None if freq is None else self.at_frequency(freq)

    def branches_for_orbit(self, orbit) -> list[Branch]:
        """The branches that can hold a measured orbit: every aerofoil branch, or the
        forced system's branch at the orbit's frequency."""
        if self.autonomous:
            return [b for k, b in self._branches.items() if str(k).startswith(MAIN)]
        b = self.at_frequency(orbit.frequency)
        return [] if b is None else [b]

    def to_json(self) -> dict:
        return {str(k): b.to_dict() for k, b in self._branches.items()}

    @classmethod
    def from_json(cls, d: dict | None) -> "Diagram | None":
        if d is None:
            return None
        return cls({(k if k.startswith(MAIN) else float(k)): Branch.from_dict(b)
                    for k, b in d.items()})
