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


def sensor_zero_lines(d: dict) -> list[str]:
    """The report's paragraph on the sensors' zero of a document's ``data`` record (none
    where every file recorded it)."""
    z = d.get("sensor_zero")
    if not z:
        return []
    if not z["identified"]:
        return [f"The files of {z['points']} point(s) do not record the sensors' zero; the "
                f"zero used: {z['method']} (`--sensor-zero identified` identifies the rest "
                "position from all points).", ""]
    where = ", ".join(f"{c} {v:.5g} ± {e:.2g}" for c, v, e in
                      zip(z["coordinates"], z["offsets"], z["std_error"]))
    moved = ""
    if z.get("incidence") is not None:
        spans = ", ".join(f"{c} {s:.3g}" for c, s in zip(z["coordinates"],
                                                         z["deflection_span"]))
        moved = (f" With it, the offset between the rest position and the load-free one "
                 f"(the zero-lift incidence) {z['incidence']:.4g}, whose static load moves "
                 f"the rest position over the points' airspeeds by {spans}; each point is "
                 "taken about its own airspeed's rest position.")
    return [f"The files of {z['points']} point(s) do not record the sensors' zero: the rig's "
            f"rest position was identified in the sensors' frame ({where}; SI units) with "
            "the mechanistic model's parameters, the equation error "
            f"{z['equation_error']:.4g} against {z['equation_error_own_means']:.4g} with "
            "each point's own mean as its zero." + moved
            + (f" Method: {z['method']}." if z.get("judged") else ""), ""]
