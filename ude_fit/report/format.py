"""How a figure is written in every report and on the terminal (one copy of each)."""

from __future__ import annotations

MISSING = "—"


def pct(x) -> str:
    """A relative error as a percentage with two decimals."""
    return MISSING if x is None else f"{100 * x:.2f} %"


def num(x, fmt: str = ".3f") -> str:
    return MISSING if x is None else format(x, fmt)


def location(entry, *, none: str = "none found", error: str = "error {:+.3f}") -> str:
    """A Hopf/fold entry {"model", "error", ...}: the model's value and its error."""
    if not entry or entry.get("model") is None:
        return none
    s = f"{entry['model']:.3f}"
    if entry.get("error") is not None:
        s += " (" + error.format(entry["error"]) + ")"
    return s


def short_location(entry) -> str:
    """As :func:`location`, for a table cell."""
    return location(entry, none=MISSING, error="{:+.3f}")
