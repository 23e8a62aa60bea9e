"""What `cbc-campaign inspect` and `cbc-campaign plot` show of a campaign file.

All three take a `Campaign` from `cbc_controller.log.read_campaign`. Amplitudes are stored in
metres (SI inside); the text table and the plot show millimetres and say so.
"""

from __future__ import annotations

import math
import os
from collections import Counter

from .log import Campaign

__all__ = ["inspect_text", "inspect_json", "plot_campaign", "parameter_label"]

_UNITS = {"airspeed": "m/s", "forcing_amplitude": "m/s²", "forcing": "m/s²"}
_DEFAULT_PARAMETER = {"flutter": "airspeed", "oscillator": "forcing_amplitude"}


def parameter_label(campaign: Campaign) -> str:
    """e.g. "airspeed (m/s)" or "forcing amplitude (m/s²)"."""
    name = next((p.get("parameter_name") for p in campaign.points if p.get("parameter_name")),
                _DEFAULT_PARAMETER.get(campaign.rig, "parameter"))
    unit = _UNITS.get(name)
    text = name.replace("_", " ")
    return f"{text} ({unit})" if unit else text


def _failed(p: dict) -> bool:
    return p.get("status", "ok") != "ok"


def _counts(points: list[dict]) -> tuple[int, int, int]:
    failed = sum(_failed(p) for p in points)
    stable = sum(bool(p.get("stable")) for p in points if not _failed(p))
    return stable, len(points) - failed - stable, failed


def _num(x, fmt: str) -> str:
    try:
        x = float(x)
    except (TypeError, ValueError):
        return "-"
    return "nan" if math.isnan(x) else format(x, fmt)


def _firmware(v) -> str:
    try:
        v = int(v)
    except (TypeError, ValueError):
        return str(v)
    return f"{v // 100}.{v % 100:02d}"


def inspect_text(campaign: Campaign) -> str:
    """A readable summary: rig, device, times, runs, point counts, and a table of the points."""
    c, meta = campaign, campaign.metadata
    ident = meta.get("identity") or {}
    lines = []

    def row(label, value):
        lines.append(f"{label:<13}{value}")

    row("file", f"{c.path}  ({c.attrs.get('format', 'cbc-campaign')} v{c.format_version})")
    device = [str(ident["model"])] if ident.get("model") else []
    if "firmware_version" in ident:
        device.append(f"firmware {_firmware(ident['firmware_version'])}")
    if "map_version" in ident:
        device.append(f"register map v{ident['map_version']}")
    if ident.get("sample_rate"):
        device.append(f"{_num(ident['sample_rate'], 'g')} Hz")
    row("rig", c.rig + (f" — {', '.join(device)}" if device else ""))
    cfg = meta.get("campaign") or {}
    name = cfg.get("name") or (cfg.get("campaign") or {}).get("name")
    if name:
        row("campaign", str(name))
    if meta.get("rig_url"):
        row("rig address", str(meta["rig_url"]))
    if meta.get("seed") is not None:
        row("seed", str(meta["seed"]))
    row("started", str(c.started or "-"))
    last = c.runs[-1] if c.runs else {}
    ended = str(c.ended or "- (no stop recorded)")
    if last.get("stop_reason"):
        ended += f"  ({last['stop_reason']})"
    row("ended", ended)
    resumes = sum(bool(r.get("resumed")) for r in c.runs)
    row("runs", f"{len(c.runs)}" + (f" ({resumes} resumed)" if resumes else ""))
    stable, unstable, failed = _counts(c.points)
    row("points", f"{len(c.points)}: {stable} stable, {unstable} unstable, {failed} failed")
    if failed:
        by_status = Counter(p.get("status", "?") for p in c.points if _failed(p))
        row("", "failed: " + ", ".join(f"{n} {s}" for s, n in sorted(by_status.items())))
    kinds = Counter(e.get("kind", "?") for e in c.events)
    row("events", ", ".join(f"{n} {k}" for k, n in sorted(kinds.items())) or "none")
    if c.incomplete:
        row("ignored", f"{c.incomplete} incomplete point group(s) (a run was killed mid-point)")
    if c.hot_journal:
        row("note", "the last commit was interrupted; shown as of the commit before it "
                    "(resuming the campaign repairs the file)")
    lines.append("")
    if not c.points:
        lines.append("(no complete points)")
        return "\n".join(lines) + "\n"
    plabel = parameter_label(c)
    pw = max(len(plabel), 10)
    head = (f"{'#':>4} {'run':>3}  {plabel:>{pw}}  {'freq (Hz)':>9}  {'amp (mm)':>9}  "
            f"{'stable':<6}  {'status':<13}  method")
    lines += [head, "-" * len(head)]
    for p in c.points:
        stable_s = "-" if _failed(p) and p.get("stable") is None else \
            ("yes" if p.get("stable") else "no")
        amp_mm = p.get("amplitude", float("nan"))
        amp_mm = amp_mm * 1e3 if isinstance(amp_mm, (int, float)) else amp_mm
        lines.append(f"{p.get('seq', p.get('index', '?')):>4} {p.get('run', 0):>3}  "
                     f"{_num(p.get('parameter'), '.4f'):>{pw}}  {_num(p.get('frequency'), '.4f'):>9}  "
                     f"{_num(amp_mm, '.4f'):>9}  {stable_s:<6}  {str(p.get('status', '?')):<13}  "
                     f"{p.get('stability_method', '-')}")
    return "\n".join(lines) + "\n"


def inspect_json(campaign: Campaign) -> list[dict]:
    """One dict per complete point, in collection order; SI units (amplitude in metres)."""
    out = []
    for p in campaign.points:
        def f(k):
            v = p.get(k)
            return float(v) if isinstance(v, (int, float)) else v
        out.append({
            "index": p.get("index"), "seq": p.get("seq"), "run": p.get("run"),
            "key": p.get("key"), "rig": p.get("rig", campaign.rig),
            "parameter": f("parameter"),
            "parameter_name": p.get("parameter_name", _DEFAULT_PARAMETER.get(campaign.rig)),
            "frequency": f("frequency"), "amplitude": f("amplitude"),
            "stable": bool(p.get("stable")), "status": p.get("status"),
            "stability_method": p.get("stability_method"),
        })
    return out


def _frequency_group(p: dict) -> float:
    f = (p.get("settings") or {}).get("frequency", p.get("frequency", float("nan")))
    try:
        f = float(f)
    except (TypeError, ValueError):
        return float("nan")
    return float(f"{f:.4g}") if math.isfinite(f) and f != 0 else f


def plot_campaign(campaign: Campaign, out_png) -> None:
    """Bifurcation diagram: amplitude (mm) against the parameter. Stable points filled, unstable
    open, failed (status not ok) grey crosses; an oscillator campaign gets one colour per forcing
    frequency, its points joined in collection order (the continuation path)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.lines import Line2D

    c = campaign
    fig = Figure(figsize=(7.5, 5.0), dpi=120)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    pts = c.points
    if c.rig == "oscillator":
        groups: dict[float, list[dict]] = {}
        for p in pts:
            groups.setdefault(_frequency_group(p), []).append(p)
        keys = sorted(groups, key=lambda k: (math.isnan(k), k))
    else:
        groups, keys = {None: list(pts)}, [None]
    if len(keys) <= 10:
        palette = [f"C{i}" for i in range(10)]
    else:
        from matplotlib import colormaps
        cmap = colormaps["viridis"]
        palette = [cmap(i / max(1, len(keys) - 1)) for i in range(len(keys))]
    handles = []
    for i, k in enumerate(keys):
        colour = palette[i % len(palette)] if c.rig == "oscillator" else "C0"
        good = [p for p in groups[k] if not _failed(p)]
        if c.rig == "oscillator" and len(good) > 1:
            ax.plot([p["parameter"] for p in good], [p["amplitude"] * 1e3 for p in good],
                    "-", color=colour, lw=0.8, alpha=0.45, zorder=1)
        st = [p for p in good if p.get("stable")]
        un = [p for p in good if not p.get("stable")]
        if st:
            ax.plot([p["parameter"] for p in st], [p["amplitude"] * 1e3 for p in st], "o",
                    color=colour, ms=6, zorder=3)
        if un:
            ax.plot([p["parameter"] for p in un], [p["amplitude"] * 1e3 for p in un], "o",
                    mfc="none", mec=colour, mew=1.4, ms=6, zorder=3)
        if c.rig == "oscillator":
            handles.append(Line2D([], [], color=colour, marker="o", lw=0.8,
                                  label=f"{k:g} Hz" if math.isfinite(k) else "frequency ?"))
    failed = [p for p in pts if _failed(p)]
    if failed:
        ax.plot([p.get("parameter", float("nan")) for p in failed],
                [p.get("amplitude", float("nan")) * 1e3 for p in failed], "x", color="0.6",
                ms=6, zorder=2)
    handles += [Line2D([], [], ls="none", marker="o", color="k", label="stable"),
                Line2D([], [], ls="none", marker="o", mfc="none", mec="k", label="unstable")]
    if failed:
        handles.append(Line2D([], [], ls="none", marker="x", color="0.6",
                              label="failed (not converged / fault)"))
    if not pts:
        ax.text(0.5, 0.5, "no complete points", transform=ax.transAxes, ha="center",
                va="center", color="0.4")
    ax.set_xlabel(parameter_label(c))
    ax.set_ylabel("amplitude (mm)")
    ax.grid(True, alpha=0.3)
    ax.legend(handles=handles, fontsize=8, loc="best",
              title="forcing frequency" if c.rig == "oscillator" and keys else None,
              title_fontsize=8)
    stable, unstable, nfail = _counts(pts)
    ax.set_title(f"{c.rig} campaign — {os.path.basename(c.path)}\n"
                 f"{len(pts)} points: {stable} stable, {unstable} unstable, {nfail} failed",
                 fontsize=10)
    fig.tight_layout()
    fig.savefig(os.fspath(out_png), format="png")
