"""ude_fit's figures: bifurcation diagrams and phase portraits, drawn from a real traced
mechanistic model of the aerofoil's true orbits, and from hand-made oscillator branches."""

from __future__ import annotations

import matplotlib.colors as mcolors
import matplotlib.image as mimage
import numpy as np
import pytest

from tests import ude_fixtures as F
from ude_fit.analysis.continuation import Branch
from ude_fit._fourier import NCOEF
from ude_fit.data.load import load
from ude_fit.data.orbit import Orbit, OrbitDataset
from ude_fit.analysis.diagram import diagram_ranges, trace_diagram
from ude_fit.training.identify import identify, training_data
from ude_fit.models.ude import UDE
from ude_fit.report.plots import (choose_orbits, diagram_figure, DPI, phase_figure, plot_diagram,
                                  plot_phase_portraits, stability_runs)

import jax  # noqa: E402  (after the imports above, before any array)

jax.config.update("jax_enable_x64", True)       # ude_fit computes in float64 (see ude_fit docs)

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
BLUE = mcolors.to_rgba("tab:blue")       # the mechanistic model's colour


@pytest.fixture(scope="module")
def flutter(tmp_path_factory):
    path = tmp_path_factory.mktemp("plots") / "f.h5"
    F.write_truth_campaign(path, "flutter", airspeeds=(18.0, 22.0, 23.6))
    ds = load(path)
    data = training_data(ds)
    mech, _ = identify(data, "flutter")
    model = UDE(mech)
    scales = np.asarray(data.y_scale)
    return ds, model, trace_diagram(model, diagram_ranges(ds), scales=scales), scales


def check_png(path, shape=None):
    raw = path.read_bytes()
    assert raw[:8] == PNG_SIGNATURE
    assert len(raw) > 10_000
    img = mimage.imread(path)
    if shape is not None:
        assert img.shape[:2] == shape
    rgb = img[..., :3]
    assert rgb.std() > 0.05                              # not one flat colour
    assert np.mean(rgb.min(axis=-1) < 0.5) > 0.005       # a fair share of dark (drawn) pixels
    return img


def is_colour(line, rgba) -> bool:
    return np.allclose(mcolors.to_rgba(line.get_color()), rgba)


def synthetic_oscillator(freqs):
    """Orbits on an S-curve p(a) = g(a) per frequency: stable on the outer parts, unstable
    in the middle, one of unknown stability; and a branch dict through them."""
    g = lambda a: 40 * (a ** 3 - 1.5 * a ** 2 + 0.7 * a)           # folds at a = 0.37, 0.63
    orbits, diagram = [], {}
    for f in freqs:
        for k, a in enumerate((0.1, 0.3, 0.5, 0.8, 1.1)):
            c = np.zeros((1, NCOEF))
            c[0, 1] = a * 1e-3 * (1 + f / 100)
            fc = np.zeros(NCOEF)
            fc[1] = g(a)
            stable = None if k == 4 else bool(abs(a - 0.5) > 0.15)
            orbits.append(Orbit(g(a), f, stable, c, fc, np.nan, 10.0, f"synthetic#{f}/{k}"))
        a = np.linspace(0.0, 1.2, 61)
        st = (3 * a ** 2 - 3 * a + 0.7) > 0
        diagram[float(f)] = Branch("oscillator", g(a), a * 1e-3 * (1 + f / 100),
                                   np.full(a.size, 1 / f), st, np.where(st, 0.5, 1.5),
                                   np.zeros((a.size, 2)), folds=[
                                       {"param": g(x), "amplitude": x * 1e-3 * (1 + f / 100),
                                        "period": 1 / f} for x in (0.3709, 0.6291)],
                                   omega=2 * np.pi * f)
    return OrbitDataset("oscillator", tuple(orbits), ("synthetic",)), diagram


# ---- pieces ---------------------------------------------------------------------------------

def test_stability_runs_split_and_join():
    runs = stability_runs([True, True, False, False, False, True])
    assert runs == [(0, 3, True), (2, 6, False), (5, 6, True)]
    for (_, stop, _), (start, _, _) in zip(runs, runs[1:]):
        assert start == stop - 1                # each piece ends where the next begins
    assert stability_runs([False] * 4) == [(0, 4, False)]
    assert stability_runs([]) == []


def test_choose_orbits_spreads_and_keeps_every_stability_class():
    ds, _ = synthetic_oscillator((21.0, 23.0, 25.0))        # 15 orbits: 9 stable, 3 unstable, 3 unknown
    idx = choose_orbits(ds, 6)
    assert len(idx) == 6 == len(set(idx))
    picked = [ds[i].stable for i in idx]
    assert picked.count(True) >= 2 and False in picked and None in picked
    stable = [i for i in range(len(ds)) if ds[i].stable is True]
    key = lambda i: (ds[i].frequency, ds[i].parameter)
    assert min(stable, key=key) in idx and max(stable, key=key) in idx    # the extremes
    assert idx == sorted(idx, key=lambda i: (*key(i), ds[i].amplitude))
    assert choose_orbits(ds, 100) == sorted(range(len(ds)), key=lambda i: (*key(i), ds[i].amplitude))


# ---- aerofoil, real traced model ------------------------------------------------------------

def test_flutter_diagram(flutter, tmp_path):
    ds, _, diag, _ = flutter
    b = diag["flutter"]
    assert b.hopf is not None and len(b.folds) == 1 and b.stable.any() and not b.stable.all()

    fig = diagram_figure(ds, {"mechanistic": diag, "ude": None}, title="t")
    assert len(fig.axes) == 1
    ax = fig.axes[0]
    lines = [ln for ln in ax.lines if is_colour(ln, BLUE)]
    # branch pieces (not at amplitude 0): solid where stable, dashed where not, continuous
    pieces = [ln for ln in lines if len(ln.get_xdata()) > 1 and np.any(ln.get_ydata() != 0)]
    assert {ln.get_linestyle() for ln in pieces} == {"-", "--"}
    assert len(pieces) == len(stability_runs(b.stable))
    for p, q in zip(pieces, pieces[1:]):
        assert p.get_xdata()[-1] == q.get_xdata()[0] and p.get_ydata()[-1] == q.get_ydata()[0]
    xs = np.concatenate([ln.get_xdata() for ln in pieces])
    assert set(xs) == set(b.param)
    # equilibrium: solid up to the Hopf airspeed, dashed beyond, and the Hopf marker at 0
    eq = [ln for ln in lines if len(ln.get_xdata()) == 2 and np.all(ln.get_ydata() == 0)]
    styles = {ln.get_linestyle(): ln.get_xdata() for ln in eq}
    assert styles["-"][1] == styles["--"][0] == pytest.approx(b.hopf["param"])
    assert any(ln.get_marker() == "*" and ln.get_xdata()[0] == b.hopf["param"] for ln in lines)
    # measured points: filled for the stable, open for the unstable
    filled = [ln for ln in ax.lines if ln.get_marker() == "o" and ln.get_markerfacecolor() != "white"]
    opened = [ln for ln in ax.lines if ln.get_marker() == "o" and ln.get_markerfacecolor() == "white"]
    assert sum(len(ln.get_xdata()) for ln in filled) == int(sum(o.stable is True for o in ds))
    assert sum(len(ln.get_xdata()) for ln in opened) == int(sum(o.stable is False for o in ds))
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    assert "mechanistic" in labels and "ude (no diagram)" in labels and "unstable" in labels

    out = tmp_path / "diagram.png"
    assert plot_diagram(out, ds, {"mechanistic": diag, "ude": None}, title="flutter") == out
    check_png(out, shape=(round(5.2 * DPI), round(8.0 * DPI)))


def test_flutter_phase_portraits(flutter, tmp_path):
    ds, model, diag, scales = flutter
    models, diagrams = {"mechanistic": model, "ude": None}, {"mechanistic": diag, "ude": None}
    fig = phase_figure(ds, models, diagrams, scales=scales, max_points=4)
    assert len(fig.axes) == 4
    idx = choose_orbits(ds, 4)
    assert {ds[i].stable for i in idx} == {True, False}
    for ax, i in zip(fig.axes, idx):
        measured, *model_lines = ax.lines
        q = ds.select([i]).sample(200)["q"][0, :, 0] * 1e3
        assert np.max(measured.get_xdata()) == pytest.approx(q.max())
        assert measured.get_linestyle() == ("-" if ds[i].stable else "--")
        assert len(model_lines) == 1 and is_colour(model_lines[0], BLUE)
        h = model_lines[0].get_xdata()
        # the model's orbit at the measured stability: near the measured size, same style
        assert 0.6 < np.ptp(h) / np.ptp(q) < 1.6
        assert model_lines[0].get_linestyle() == measured.get_linestyle()
        assert ax.texts and ax.texts[0].get_text() == "ude: no orbit"

    out = tmp_path / "phase.png"
    assert plot_phase_portraits(out, ds, {"mechanistic": model}, {"mechanistic": diag},
                                scales=scales) == out
    check_png(out)


# ---- oscillator: one panel per frequency ----------------------------------------------------

def test_oscillator_diagram_one_axes_per_frequency(tmp_path):
    freqs = (19.0, 21.0, 23.0, 25.0)
    ds, diagram = synthetic_oscillator(freqs)
    fig = diagram_figure(ds, {"mechanistic": diagram, "ude": None})
    assert len(fig.axes) == 4                       # 2 x 3 grid, the spare panels removed
    assert [ax.get_title() for ax in fig.axes] == ["19 Hz", "21 Hz", "23 Hz", "25 Hz"]
    for ax, f in zip(fig.axes, freqs):
        blue = [ln for ln in ax.lines if is_colour(ln, BLUE) and ln.get_marker() in ("None", "")]
        assert len(blue) == 3 and [ln.get_linestyle() for ln in blue] == ["-", "--", "-"]
        assert np.max(np.concatenate([ln.get_ydata() for ln in blue])) == pytest.approx(
            1.2 * (1 + f / 100))
        folds = [ln for ln in ax.lines if ln.get_marker() == "D"]
        assert len(folds) == 2
        unknown = [ln for ln in ax.lines if ln.get_marker() == "s"]     # grey squares
        assert sum(len(ln.get_xdata()) for ln in unknown) == 1
        assert all(np.allclose(mcolors.to_rgba(ln.get_markerfacecolor()),
                               mcolors.to_rgba("0.6")) for ln in unknown)
    # a frequency that only a model's diagram has still gets its panel
    extra = {**diagram, 30.0: diagram[25.0]}
    assert len(diagram_figure(ds, {"mechanistic": extra}).axes) == 5
    assert len(diagram_figure(ds.at_frequency(21.0), {"ude": None}).axes) == 1

    out = tmp_path / "osc.png"
    plot_diagram(out, ds, {"mechanistic": diagram, "ude": None}, title="oscillator")
    check_png(out)


def test_oscillator_phase_portraits_without_models(tmp_path):
    ds, diagram = synthetic_oscillator((21.0, 23.0))
    fig = phase_figure(ds, {"ude": None}, {"ude": None}, scales=np.ones(2), max_points=5)
    assert len(fig.axes) == 5
    for ax in fig.axes:
        assert len(ax.lines) == 1 and ax.texts[0].get_text() == "ude: no orbit"
        assert ax.get_xlabel() == "displacement x (mm)"
    out = tmp_path / "osc_phase.png"
    plot_phase_portraits(out, ds, {"ude": None}, {"ude": None}, scales=np.ones(2))
    check_png(out)


def test_blank_png_is_rejected(tmp_path):
    """The non-blank check itself can fail."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    fig = Figure(figsize=(8, 5))
    FigureCanvasAgg(fig)
    fig.savefig(tmp_path / "blank.png", dpi=DPI)
    with pytest.raises(AssertionError):
        check_png(tmp_path / "blank.png")
