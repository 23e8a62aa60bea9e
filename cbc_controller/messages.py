"""What a CBC plan can ask of the engine.

A plan is a generator that yields these messages and receives each one's result
(`result = yield Settle(...)`). It never touches a socket, so a CBC method can be
tested against an in-process simulated rig, and the engine against a trivial plan.
Exceptions from the rig side (a latched fault, a rig restart) are thrown into the
plan at its current `yield`, so the plan decides what a fault means for its point.
"""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass(frozen=True)
class Configure:
    """Write settings (register names -> values) to the rig, validated together."""
    settings: dict


@dataclass(frozen=True)
class Arm:
    pass


@dataclass(frozen=True)
class Disarm:
    pass


@dataclass(frozen=True)
class Settle:
    """Wait until the board has completed `periods` estimator periods after the last
    Configure, then return an `Estimate`. `record_s` > 0 also records that many rig
    seconds of full-rate samples ending at the estimate (returned in Estimate.samples)."""
    periods: int
    record_s: float = 0.0


@dataclass(frozen=True)
class Reseed:
    """Start a reproducible segment of the campaign: on a lockstep rig the simulation restarts
    from rest, disarmed, its noise streams seeded from `seed` (the rig's `noise_seed`), so
    what follows depends only on the seed and the plan, not on what the rig did before (a
    resumed campaign measures the same numbers as one never interrupted). Settings stay. A
    rig running in real time is a physical experiment: there nothing happens."""
    seed: int


@dataclass(frozen=True)
class Emit:
    """Publish a document (a collected point, a note) to the subscribers."""
    kind: str
    doc: dict


@dataclass
class Estimate:
    """The board's Fourier estimates after settling."""
    fourier: dict                 # channel -> {"mean": array(15), "var": array(15)}
    frequency: float              # Hz (mean period frequency over navg periods)
    frequency_var: float
    periods: int                  # board period counter
    rig_time: float               # rig seconds since start (sample_seq / rate)
    samples: dict | None = None   # field -> array, when recorded
    waited_s: float = 0.0         # rig seconds spent waiting for this estimate


class RigFault(RuntimeError):
    """The rig latched a fault (code, text); the engine has disarmed it."""

    def __init__(self, code: int, text: str):
        super().__init__(f"rig fault {code}: {text}")
        self.code = code
        self.text = text


class RigRestarted(RuntimeError):
    """The link was lost and re-established (the rig may have restarted); the
    engine has re-applied the settings it knew, but the point in progress is void."""


@dataclass
class PlanContext:
    """What a plan knows about the campaign it runs in."""
    config: dict
    identity: dict
    done: set = field(default_factory=set)     # keys of points already in the file (resume)
    previous: list = field(default_factory=list)  # those points' summaries, in order
