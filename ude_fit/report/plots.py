"""Figures of fitted models against the measured orbits: bifurcation diagrams and phase portraits.

Figures are built as ``matplotlib.figure.Figure`` objects drawn by the Agg canvas directly,
so nothing here touches pyplot's global state or the user's chosen backend.

* :func:`diagram_figure` / :func:`plot_diagram`: measured points (filled: stable, open:
  unstable, grey: unknown) and every model's branch (solid: stable, dashed: unstable),
  folds, and for the aerofoil the Hopf point with the equilibrium branch at amplitude 0.
  Aerofoil: one axes (airspeed vs heave amplitude); oscillator: one axes per frequency.
* :func:`phase_figure` / :func:`plot_phase_portraits`: a few measured orbits spread over
  the parameter, each with every model's orbit at the same parameter and stability.
"""

from __future__ import annotations

import math

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.lines import Line2D

from .._systems import system_kind
from ..analysis.continuation import Branch
from ..analysis.diagram_type import Diagram
from ..analysis.metrics import model_orbit
from ..discovery.explain import EQUATIONS


MM = 1e3                                    # m -> mm
DPI = 120
_FIXED_COLOURS = {"mechanistic": "tab:blue", "ude": "tab:red"}
_SPARE_COLOURS = ("tab:green", "tab:purple", "tab:orange", "tab:brown", "tab:pink", "tab:olive")
_DATA = dict(color="black", markersize=6, linestyle="none", zorder=5)
_UNKNOWN = "0.6"


def _colours(names) -> dict:
    spare = iter(_SPARE_COLOURS)
    return {n: _FIXED_COLOURS.get(n) or next(spare, "tab:gray") for n in names}


def stability_runs(stable) -> list[tuple[int, int, bool]]:
    """Runs of equal stability as (start, stop, stable), ``stop`` exclusive; each run but the
    last also takes the next run's first point, so that drawn one after another the pieces
    make one continuous curve."""
    s = np.asarray(stable, bool)
    if s.size == 0:
        return []
    cuts = np.flatnonzero(s[1:] != s[:-1]) + 1
    starts = np.concatenate([[0], cuts])
    ends = np.concatenate([cuts, [s.size]])
    return [(int(a), int(min(b + 1, s.size)), bool(s[a])) for a, b in zip(starts, ends)]


def _branch_for(diagram, freq: float | None) -> Branch | None:
    return Diagram.of(diagram).branch_for(freq) if diagram else None


def _draw_branch(ax, b: Branch, colour: str) -> None:
    x, y = np.asarray(b.param, float), np.asarray(b.amplitude, float) * MM
    for i0, i1, st in stability_runs(b.stable):
        ax.plot(x[i0:i1], y[i0:i1], color=colour, lw=1.8, ls="-" if st else "--", zorder=3)
    for f in b.folds:
        ax.plot(f["param"], f["amplitude"] * MM, marker="D", ms=5, color=colour,
                mec="black", mew=0.6, ls="none", zorder=4)


def _draw_points(ax, ds) -> None:
    x, y = ds.parameters(), ds.amplitudes() * MM
    st = [o.stable for o in ds]
    pick = lambda v: np.array([s is v for s in st], bool)
    ax.plot(x[pick(True)], y[pick(True)], marker="o", mfc="black", **_DATA)
    ax.plot(x[pick(False)], y[pick(False)], marker="o", mfc="white", mew=1.5, **_DATA)
    unk = pick(None)
    ax.plot(x[unk], y[unk], marker="s", mfc=_UNKNOWN, mec=_UNKNOWN, ls="none", ms=6, zorder=5)


def _legend_handles(ds, names, colours, missing, system) -> list:
    h = [Line2D([], [], color=colours[n], lw=1.8 if n not in missing else 1.0,
                ls="-" if n not in missing else ":",
                label=n if n not in missing else f"{n} (no diagram)") for n in names]
    h += [Line2D([], [], color="black", lw=1.5, label="stable"),
          Line2D([], [], color="black", lw=1.5, ls="--", label="unstable")]
    st = [o.stable for o in ds]
    if True in st:
        h.append(Line2D([], [], marker="o", mfc="black", label="measured, stable", **_DATA))
    if False in st:
        h.append(Line2D([], [], marker="o", mfc="white", mew=1.5,
                        label="measured, unstable", **_DATA))
    if None in st:
        h.append(Line2D([], [], marker="s", mfc=_UNKNOWN, mec=_UNKNOWN, ls="none",
                        label="measured, stability unknown"))
    h.append(Line2D([], [], marker="D", ms=5, color="0.5", mec="black", ls="none", label="fold"))
    if system_kind(system).autonomous:
        h.append(Line2D([], [], marker="*", ms=11, color="0.5", mec="black", ls="none",
                        label="Hopf (equilibrium: amplitude 0)"))
    return h


def _grid(n: int, width: float, height: float, extra_w: float = 0.0, max_cols: int = 3):
    """A constrained-layout figure with exactly max(n, 1) axes on a grid of <= max_cols columns."""
    cols = max(1, min(n, max_cols))
    rows = max(1, math.ceil(n / cols))
    fig = Figure(figsize=(width * cols + extra_w, height * rows + 0.5), layout="constrained")
    axes = fig.subplots(rows, cols, squeeze=False).ravel()
    for ax in axes[max(n, 1):]:
        ax.remove()
    return fig, list(axes[:max(n, 1)])


def _frequencies(ds, diagrams) -> list[float]:
    out = [float(f) for f in ds.frequencies_group()] if len(ds) else []
    for d in diagrams.values():
        for f in (Diagram.of(d).frequencies() if d else []):
            if not any(abs(float(f) - g) <= 1e-6 * max(1.0, g) for g in out):
                out.append(float(f))
    return sorted(out)


def diagram_figure(ds, diagrams: dict, *, title: str = "") -> Figure:
    """The bifurcation diagram figure (see :func:`plot_diagram`); one axes per panel."""
    names = list(diagrams)
    colours = _colours(names)
    missing = {n for n, d in diagrams.items() if not d}
    if ds.kind.autonomous:
        fig = Figure(figsize=(8.0, 5.2), layout="constrained")
        ax = fig.add_subplot()
        branches = [b for b in (_branch_for(diagrams[n], None) for n in names) if b is not None]
        xs = np.concatenate([ds.parameters(), *(np.asarray(b.param, float) for b in branches),
                             [b.hopf["param"] for b in branches if b.hopf]])
        lo, hi = (float(xs.min()), float(xs.max())) if xs.size else (0.0, 1.0)
        pad = 0.05 * max(hi - lo, 1.0)
        lo, hi = lo - pad, hi + pad
        for n in names:
            b = _branch_for(diagrams[n], None)
            if b is None:
                continue
            _draw_branch(ax, b, colours[n])
            for isola in Diagram.of(diagrams[n]).isolas:
                _draw_branch(ax, isola, colours[n])
            if b.hopf:
                vh = b.hopf["param"]
                ax.plot([lo, vh], [0, 0], color=colours[n], lw=1.8, zorder=3)
                ax.plot([vh, hi], [0, 0], color=colours[n], lw=1.8, ls="--", zorder=3)
                ax.plot(vh, 0.0, marker="*", ms=13, color=colours[n], mec="black",
                        ls="none", zorder=6, clip_on=False)
        _draw_points(ax, ds)
        ax.set_xlim(lo, hi)
        ax.set_xlabel("airspeed (m/s)")
        ax.set_ylabel("heave amplitude, first harmonic (mm)")
        ax.set_ylim(bottom=-0.03 * max(ax.get_ylim()[1], 1e-9))
        ax.grid(alpha=0.3)
        ax.legend(handles=_legend_handles(ds, names, colours, missing, "flutter"),
                  loc="best", fontsize=8, framealpha=0.9)
        axes = [ax]
    else:
        freqs = _frequencies(ds, diagrams)
        fig, axes = _grid(len(freqs), 4.3, 3.5, extra_w=2.2)
        for ax, f in zip(axes, freqs):
            for nm in names:
                b = _branch_for(diagrams[nm], f)
                if b is not None:
                    _draw_branch(ax, b, colours[nm])
            _draw_points(ax, ds.at_frequency(f))
            ax.set_title(f"{f:g} Hz")
            ax.set_xlabel("forcing amplitude (m/s²)")
            ax.set_ylabel("displacement amplitude (mm)")
            ax.set_xlim(left=0.0)
            ax.set_ylim(bottom=0.0)
            ax.grid(alpha=0.3)
        fig.legend(handles=_legend_handles(ds, names, colours, missing, "oscillator"),
                   loc="outside right upper", fontsize=8)
    if title:
        fig.suptitle(title)
    return fig


def _save(fig: Figure, path) -> None:
    FigureCanvasAgg(fig)
    fig.savefig(path, dpi=DPI, format="png")


def plot_diagram(path, ds, diagrams: dict, *, title: str = ""):
    """Write the bifurcation diagram of ``diagrams`` (model name -> diagram dict or None)
    against the measured points of ``ds`` as a PNG; returns ``path``."""
    _save(diagram_figure(ds, diagrams, title=title), path)
    return path


def choose_orbits(ds, max_points: int = 6) -> list[int]:
    """Indices of up to ``max_points`` measured orbits spread over the parameter, with every
    stability class present (stable, unstable, unknown) represented where there is room."""
    n = len(ds)
    if n <= max_points:
        idx = list(range(n))
    else:
        groups = [[i for i in range(n) if ds[i].stable is v] for v in (True, False, None)]
        groups = [sorted(g, key=lambda i: (ds[i].frequency, ds[i].parameter))
                  for g in groups if g]
        quota = [1 if max_points >= len(groups) else 0 for _ in groups]
        while sum(quota) < max_points:     # hand out the rest in proportion to group size
            k = max(range(len(groups)), key=lambda j: (len(groups[j]) - quota[j]) / len(groups[j])
                    if quota[j] < len(groups[j]) else -1)
            quota[k] += 1
        idx = []
        for g, q in zip(groups, quota):
            if q:
                idx += [g[int(j)] for j in np.unique(np.round(np.linspace(0, len(g) - 1, q)))]
    return sorted(idx, key=lambda i: (ds[i].frequency, ds[i].parameter, ds[i].amplitude))


def phase_figure(ds, models: dict, diagrams: dict, *, scales, max_points: int = 6) -> Figure:
    """The phase-portrait figure (see :func:`plot_phase_portraits`); one axes per orbit."""
    idx = choose_orbits(ds, max_points)
    names = list(dict.fromkeys([*models, *diagrams]))
    colours = _colours(names)
    flutter = ds.kind.autonomous
    fig, axes = _grid(len(idx), 4.0, 3.5)
    for ax, i in zip(axes, idx):
        o = ds[i]
        s = ds.select([i]).sample(200)
        q, qd = s["q"][0, :, 0] * MM, s["qdot"][0, :, 0] * MM
        ax.plot(np.append(q, q[0]), np.append(qd, qd[0]), color="black", lw=2.4,
                ls="-" if o.stable is not False else "--", label="measured", zorder=4)
        notes = []
        for nm in names:
            model = models.get(nm)
            d = diagrams.get(nm)
            orb = None
            if model is not None and d:
                orb = model_orbit(model, d, o, scales=scales)
            if orb is None:
                notes.append(f"{nm}: no orbit")
                continue
            y = np.asarray(orb["samples"], float)
            nd = y.shape[1] // 2
            x, v = y[:, 0] * MM, y[:, nd] * MM
            ax.plot(np.append(x, x[0]), np.append(v, v[0]), color=colours[nm], lw=1.5,
                    ls="-" if orb["stable"] else "--", label=nm, zorder=5)
        stab = {True: "stable", False: "unstable", None: "stability unknown"}[o.stable]
        where = (f"V = {o.parameter:.4g} m/s" if flutter
                 else f"{o.frequency:g} Hz, A = {o.parameter:.4g} m/s²")
        ax.set_title(f"{where}, {stab}", fontsize=9)
        if notes:
            ax.text(0.02, 0.02, "\n".join(notes), transform=ax.transAxes, fontsize=8,
                    va="bottom", ha="left", color="0.3")
        ax.set_xlabel("heave h (mm)" if flutter else "displacement x (mm)")
        ax.set_ylabel("heave velocity (mm/s)" if flutter else "velocity (mm/s)")
        ax.grid(alpha=0.3)
    if not idx:
        axes[0].text(0.5, 0.5, "no measured orbits", ha="center", va="center",
                     transform=axes[0].transAxes)
    handles = [Line2D([], [], color="black", lw=2.4, label="measured")]
    handles += [Line2D([], [], color=colours[nm], lw=1.5, label=nm) for nm in names]
    handles += [Line2D([], [], color="0.4", lw=1.5, ls="--", label="unstable orbit")]
    fig.legend(handles=handles, loc="outside lower center", ncols=len(handles), fontsize=8)
    fig.suptitle("measured orbits and the models' orbits at the same parameter and stability",
                 fontsize=10)
    return fig


def plot_phase_portraits(path, ds, models: dict, diagrams: dict, *, scales, max_points: int = 6):
    """Write phase portraits of up to ``max_points`` measured orbits, each with every model's
    orbit (``models``: name -> UDE, ``diagrams``: name -> diagram) at the same parameter and
    measured stability, as a PNG; returns ``path``."""
    _save(phase_figure(ds, models, diagrams, scales=scales, max_points=max_points), path)
    return path


_STATE_LABELS = {"flutter": (("h", "heave h (mm)", MM), ("al", "pitch α (deg)", 180 / math.pi),
                             ("hd", "heave rate h' (mm/s)", MM),
                             ("ad", "pitch rate α' (deg/s)", 180 / math.pi)),
                 "oscillator": (("x", "displacement x (mm)", MM),
                                ("xd", "velocity x' (mm/s)", MM))}


def residual_figure(explanation, *, parameter_label: str) -> Figure:
    """What the mechanistic model leaves on every sample of the measured orbits, against
    each state, one row per equation, coloured by the bifurcation parameter: the picture
    that points at a missing effect (a cubic bend, a step at zero velocity, a flat zone)."""
    system = explanation.system
    S = explanation.residual["states"]
    eqs = sorted(explanation.residual["residual"])
    states = _STATE_LABELS[system]
    fig = Figure(figsize=(3.2 * len(states), 2.8 * len(eqs) + 0.4), layout="constrained")
    axes = fig.subplots(len(eqs), len(states), squeeze=False)
    par = np.asarray(S["V"] if system_kind(system).autonomous else S["w"] / (2 * math.pi))
    for i, eq in enumerate(eqs):
        r = np.asarray(explanation.residual["residual"][eq])
        sel = explanation.selections[i]
        top = next((e["name"] for e in sel.effects if e["significant"]), "nothing significant")
        for j, (key, label, k) in enumerate(states):
            ax = axes[i, j]
            sc = ax.scatter(np.asarray(S[key]) * k, r, c=par, s=4, cmap="viridis",
                            rasterized=True)
            ax.axhline(0.0, color="0.5", lw=0.6)
            ax.set_xlabel(label)
            if j == 0:
                ax.set_ylabel(f"residual {EQUATIONS[system][eq]}")
            ax.grid(alpha=0.3)
        axes[i, 0].set_title(f"top candidate: {top}", loc="left", fontsize=9)
    fig.colorbar(sc, ax=axes[:, -1].tolist(), label=parameter_label)
    return fig


def parameter_label(system: str) -> str:
    """The residual figure's colour axis: the parameter each orbit was measured at."""
    return system_kind(system).diagram_axis


def plot_residuals(path, explanation, *, parameter_label: str):
    """Write :func:`residual_figure` as a PNG; returns ``path``."""
    _save(residual_figure(explanation, parameter_label=parameter_label), path)
    return path


def shapes_figure(location) -> Figure:
    """The located shape functions: per equation (rows) and state (columns), the partial
    residual on the samples, the penalised spline with its two-standard-error band, and
    the named class's form where one was fitted: the picture a dynamicist reads."""
    eqs = location.equations
    n_st = max(len(e.shapes) for e in eqs)
    fig = Figure(figsize=(2.9 * n_st, 2.5 * len(eqs) + 0.3), layout="constrained")
    axes = fig.subplots(len(eqs), n_st, squeeze=False)
    for i, e in enumerate(eqs):
        for j, s in enumerate(sorted(e.shapes, key=lambda s: s.state)):
            ax = axes[i, j]
            ax.scatter(s.samples, s.partial, s=2, color="0.6", rasterized=True)
            colour = "C3" if s.significant else "C0"
            ax.fill_between(s.grid, s.value - 2 * s.band, s.value + 2 * s.band,
                            color=colour, alpha=0.25, lw=0)
            ax.plot(s.grid, s.value, color=colour, lw=1.5)
            ax.set_xlabel(s.name)
            tag = f"p = {s.p_value:.2g}" + (" (significant)" if s.significant else "")
            ax.set_title(tag, fontsize=8, loc="left")
            if j == 0:
                ax.set_ylabel(f"{e.name}: shape (linear part removed)")
            ax.grid(alpha=0.3)
    return fig


def plot_shapes(path, location):
    """Write :func:`shapes_figure` as a PNG; returns ``path``."""
    _save(shapes_figure(location), path)
    return path
