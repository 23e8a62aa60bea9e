"""The steps every plan shares, written once: start a reproducible segment, configure and
settle, ride out a fault, retry a step that faults, emit a point (numbered on from the file,
never a key twice)."""

from __future__ import annotations

import hashlib

import numpy as np

from ..messages import Configure, Emit, Reseed, RigFault, RigRestarted, Settle

FAULTS = (RigFault, RigRestarted)     # what the engine throws into a plan at its yield


def note(text: str, **fields) -> Emit:
    """A note document (free text, plus any fields a reader may use)."""
    return Emit("note", {"text": text, **fields})


def start_segment(ctx, identity: str) -> Reseed:
    """The message that starts the segment `identity` (an airspeed, a frequency's sweep: the
    unit a resumed campaign redoes): its noise streams come from the campaign's seed and the
    segment's identity alone, so a segment measured after a resume is the same as in the
    campaign never interrupted."""
    seed = ((ctx.config or {}).get("campaign") or {}).get("seed", 0)
    digest = hashlib.sha256(f"{seed}/{identity}".encode()).digest()
    return Reseed(int.from_bytes(digest[:4], "little") & 0x7FFFFFFF)   # the register's range


def configure_and_settle(settings: dict, periods: int, record_s: float = 0.0):
    """Generator: write the settings, wait `periods` estimator periods (recording `record_s`
    rig seconds at the end); returns the Estimate."""
    yield Configure(settings)
    return (yield Settle(periods=periods, record_s=record_s))


def lost_to_fault(*messages):
    """Generator: send the messages in turn; returns the fault (RigFault or RigRestarted)
    thrown into one of them, the rest unsent, or None when none was."""
    try:
        for msg in messages:
            yield msg
    except FAULTS as exc:
        return exc
    return None


def retry(step, tries: int):
    """Generator: run the generator `step()` until one run ends without a fault thrown into
    it, at most `tries` times; True once one has."""
    for _ in range(tries):
        try:
            yield from step()
            return True
        except FAULTS:
            continue
    return False


class PointLog:
    """The points a plan emits, numbered on from those already in the file; a key already
    there (a resumed campaign, or a point measured before a lost link made the plan repeat
    its airspeed) is not emitted again."""

    def __init__(self, ctx):
        self.done = set(ctx.done or ())
        self.index = len(ctx.previous or [])

    def emit(self, key: str, make_doc):
        """Generator: emit `make_doc(index)` as the point `key` unless the file has it;
        returns whether it was emitted."""
        if key in self.done:
            return False
        yield Emit("point", make_doc(self.index))
        self.done.add(key)
        self.index += 1
        return True


def point_doc(*, index: int, key: str, rig: str, parameter: float, parameter_name: str,
              frequency: float, amplitude: float, stable: bool, stability_method: str,
              converged: bool, settings: dict, estimate, dc: float, history: list,
              wall_time: float, extra: dict) -> dict:
    """A point document: the plan's numbers and the estimate it ends on, with the board's
    Fourier estimates and the full-rate record (and its control and response RMS, the
    response's about `dc`, in `extra`)."""
    ts = estimate.samples or {}
    if ts.get("x") is not None and len(ts["x"]):
        extra["control_rms"] = float(np.sqrt(np.mean(np.asarray(ts["control"]) ** 2)))
        extra["response_rms"] = float(np.sqrt(np.mean((np.asarray(ts["x"]) - dc) ** 2)))
        extra["gap_records"] = int(ts.get("gap_records", 0))
    return {
        "index": index, "key": key, "rig": rig, "parameter": float(parameter),
        "parameter_name": parameter_name, "frequency": float(frequency),
        "amplitude": float(amplitude), "stable": bool(stable),
        "stability_method": stability_method,
        "status": "ok" if converged else "not_converged",
        "settings": settings,
        "fourier": {ch: {"mean": np.asarray(v["mean"]), "var": np.asarray(v["var"])}
                    for ch, v in estimate.fourier.items()},
        "history": history, "rig_time": estimate.rig_time, "wall_time": wall_time,
        "timeseries": {k: np.asarray(v) for k, v in ts.items() if k != "gap_records"},
        "extra": extra,
    }
