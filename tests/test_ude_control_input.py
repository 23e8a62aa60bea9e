"""The holding control as a known input (issue 17): the recorded control comes in with the
orbit in its phase frame, its gain is 1 for a force record, given, or identified, and a
campaign held deliberately invasively is fitted as orbits of the controlled system.

Truth: a lee2020-format file with a control of known amplitude and phase; the simulated
rig held on its own orbits with the target's amplitude off the truth's (the board then
holds an orbit of the controlled system; the control it applies is the recorded one) and
the rig's own open-loop orbits at the same airspeeds.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from tests import ude_fixtures as F
from tests.invasive_cases import criterion, criterion_figures, fit_cases, mechanistic_cases
from tests.test_ude_realdata import write_lee
from ude_fit import cli
from ude_fit._fourier import K
from ude_fit.data import load
from ude_fit.fitting import prepare
from ude_fit.mechanistic_stage import identify_mechanistic
from ude_fit.models.mechanistic import FLUTTER_NOMINAL
from ude_fit.training.control import against_heave_stiffness, with_control
from ude_fit.training.identify import INPUT_GAIN

import jax  # noqa: E402  (after the imports above, before any array)

pytestmark = pytest.mark.minutes(11)   # CI order: tests/conftest.py

jax.config.update("jax_enable_x64", True)

AIRSPEEDS = (19.0, 21.0, 23.0, 25.5)
INVASIVE = 0.15


@pytest.fixture(scope="module")
def invasive(tmp_path_factory):
    """A campaign held with the target 15 % off every truth orbit (alternately above and
    below), sigma = 0, and the truth records."""
    path = tmp_path_factory.mktemp("invasive") / "invasive.h5"
    truth = F.write_truth_campaign(path, "flutter", airspeeds=AIRSPEEDS, sigma=0.0,
                                   record_s=2.0, invasive=INVASIVE)
    return path, truth


def test_the_control_comes_in_the_orbits_frame(tmp_path):
    """lee2020 format: a control c cos(phi + 0.3) V against the heave's cos(phi): the
    orbit's control is that cosine in the frame where the heave is +A cos(phi), without
    its mean (the heave's was removed)."""
    write_lee(tmp_path / "CBC_v1.mat", control=4e-3)
    (o,) = load(tmp_path, "flutter")
    assert o.control.shape == (2 * K + 1,)
    assert o.control[0] == 0.0
    assert o.control[1] == pytest.approx(4e-3 * math.cos(0.3), rel=1e-6)
    assert o.control[1 + K] == pytest.approx(-4e-3 * math.sin(0.3), rel=1e-6)
    assert np.abs(o.control[np.r_[2:K + 1, K + 2:2 * K + 1]]).max() < 1e-9


def test_gain_is_identified_from_the_orbits(invasive):
    """The rig's control is a force (N), gain 1: identified free, the gain comes out of
    the right sign and size but not exactly 1 (measured 1.33 on seven airspeeds, 1.54 on
    these four: the quasi-steady model leaves the unsteady lag's force to the residual,
    and the control, which follows the orbit, takes part of it), and a record in another
    unit (the same control divided by 5) gives 5 times that gain, the other parameters
    unchanged."""
    ds = load([invasive[0]], "flutter")
    assert all(o.holding.control_unit == "N" and o.holding.invasive for o in ds)
    data = prepare(ds, "flutter", None, 32)[1]
    _, one = identify_mechanistic(with_control(data, ds, 1.0), "flutter", free_input=True)
    _, fifth = identify_mechanistic(with_control(data, ds, 0.2), "flutter", free_input=True)
    g = one["parameters"][INPUT_GAIN]
    assert 0.5 < g < 2.0, g
    assert fifth["parameters"][INPUT_GAIN] == pytest.approx(5 * g, rel=1e-8)
    for name in ("c_h", "k_h", "c_alpha", "k_alpha"):
        assert fifth["parameters"][name] == pytest.approx(one["parameters"][name], rel=1e-8)


@pytest.mark.parametrize("argv, message", [
    (["--system", "oscillator", "--control-input"], "--control-input applies to --system "
     "flutter only"),
    (["--system", "flutter", "--control-gain", "2"], "--control-gain needs --control-input"),
    (["--system", "flutter", "--control-input", "--control-gain", "0"],
     "--control-gain must be a finite number other than 0"),
])
def test_control_options_are_checked(tmp_path, capsys, argv, message):
    write_lee(tmp_path / "CBC_v1.mat", control=4e-3)
    out = tmp_path / "out"
    rc = cli.main(["fit", str(tmp_path / "CBC_v1.mat"), *argv, "--out", str(out), "--quiet"])
    err = capsys.readouterr().err
    assert rc == 2 and message in err and len(err.strip().splitlines()) == 1, err
    assert not out.exists()


@pytest.mark.parametrize("command", ["loop", "refine", "explain"])
def test_the_discovery_commands_check_the_control_options(tmp_path, capsys, command):
    """The loop's commands take the control input as the fit does, with the same checks:
    each mistake ends with one line before anything is written."""
    write_lee(tmp_path / "CBC_v1.mat", control=4e-3)
    for system, flags, message in (
            ("flutter", ["--control-gain", "2"], "--control-gain needs --control-input"),
            ("flutter", ["--control-input", "--control-gain", "0"],
             "--control-gain must be a finite number other than 0"),
            ("oscillator", ["--control-input"], "--control-input applies to --system "
             "flutter only")):
        out = tmp_path / f"out_{command}"
        extra = (["--add", "heave_cubic" if system == "flutter" else "cubic_damping"]
                 if command == "refine" else [])
        rc = cli.main([command, str(tmp_path / "CBC_v1.mat"), "--system", system, *flags,
                       *extra, "--out", str(out), "--quiet"])
        err = capsys.readouterr().err
        assert rc == 2 and message in err and len(err.strip().splitlines()) == 1, err
        assert not out.exists()


# ---- what a model of controlled points is judged by ----

def test_a_point_is_met_under_the_control_only_where_the_diagram_has_its_stability():
    """analysis.controlled.judged: a point's error is its orbit's under the control; the
    point is missed where that orbit does not close, and where the open-loop diagram has no
    orbit of the point's stability there (a model with no limit cycle meets every point
    under a known forcing); the Hopf point and folds stay the diagram's."""
    from ude_fit.analysis.controlled import ControlledOrbits, judged
    from ude_fit.analysis.metrics_type import BranchErrors, ModelMetrics, PointError
    a_max = 0.04
    measured = [(20.0, 0.01, False), (21.0, 0.02, True), (22.0, 0.03, True),
                (23.0, 0.04, True)]
    diagram = [PointError(v, 2.4, a, s, model=a + 0.004, error=0.1, trajectory=0.1,
                          model_stable=s) for v, a, s in measured]
    diagram[1] = PointError(21.0, 2.4, 0.02, True)          # the diagram's orbit unstable
    metrics = ModelMetrics.of(BranchErrors.of(diagram, a_max),
                              {"hopf": 24.0, "fold": 18.5, "folds": [18.5], "isolas": 0,
                               "isola_folds": []}, {}, "given")
    under = [PointError(v, 2.4, a, s, model=a + 4e-4, error=0.01) for v, a, s in measured]
    under[2] = PointError(22.0, 2.4, 0.03, True)             # no closed orbit
    controlled = ControlledOrbits(BranchErrors.of(under, a_max))
    j = judged(metrics, controlled)
    assert [p.missed for p in j.points] == [False, True, True, False]
    assert j.summary.missed == 2 and j.summary.branch_rms == pytest.approx(0.01)
    assert j.summary.branch_rms_with_missed == pytest.approx(
        math.sqrt((0.01 ** 2 + 0.5 ** 2 + 0.75 ** 2 + 0.01 ** 2) / 4))
    assert j.points[0].model == pytest.approx(0.01 + 4e-4)
    assert (j.hopf, j.fold, j.folds) == (metrics.hopf, metrics.fold, metrics.folds)
    assert judged(metrics, None) is metrics
    with pytest.raises(ValueError, match="3 orbits under the control for 4 points"):
        judged(metrics, ControlledOrbits(BranchErrors.of(under[:3], a_max)))


# ---- fits: the invasive campaign with and without the control, the non-invasive one ----

LOOSE = 0.05        # the target 5 % off the truth orbit: orbits held 2-14 % off theirs


@pytest.fixture(scope="module")
def fits(tmp_path_factory):
    """One start of the default fit on the invasive campaign with the control as an input
    (tests/invasive_cases.py). The issue's comparison with a fit to the non-invasive
    campaign (Hopf and fold within 0.1 m/s of its, error at most 1.5 times its) is not met
    on this campaign by the default's kept UDE and is measured by
    benchmarks/invasive_benchmark.py, not here (seed 0: with the control, Hopf 24.09 and
    fold 16.79 against that fit's 23.99 and 16.26 m/s, error 0.37 % against 0.12 %); the
    mechanistic model with the wake added meets it (below), and the default fit meets it
    on the CBC controller's own loose campaign (tests/test_ude_invasive_cbc.py, which also
    has the fit without the control)."""
    out = fit_cases(tmp_path_factory.mktemp("fits"), LOOSE, names=("loose+control",))
    for name, (r, m, _, _) in out.items():
        assert r.ude is not None and m is not None, name
    return {name: (r, m) for name, (r, m, _, _) in out.items()}


def test_the_control_input_recovers_the_open_loop_diagram(fits):
    """The invasive campaign's points are 2-14 % off the open-loop orbits; fitted with the
    control as a known input, every truth orbit is found and the open-loop diagram lies
    within 1 % of the truth's amplitudes (measured 0.37 %; the same fit without the control
    2.56 %, benchmarks/invasive_benchmark.py); the identification records the gain and
    where it came from."""
    with_u = fits["loose+control"][1].summary
    assert with_u.missed == 0 and with_u.branch_rms <= 0.01, with_u
    ident = fits["loose+control"][0].to_json()["mechanistic"]["identification"]
    control = dict(ident["control"])
    control.pop("against_heave_stiffness")
    assert control == {"unit": "N", "gain": 1.0,
                       "gain_source": "the control is recorded as a force (N)"}


def test_the_fit_with_the_control_judges_its_starts_under_the_control(fits):
    """With the control as an input the adequacy compares each model's orbits under the
    recorded control with the points (analysis.controlled.judged): the start's orbits under
    the control meet the invasively held points at least 5 times closer than its open-loop
    diagram does (measured 0.12 % against 2.17 %) and at least 10 times closer than the
    mechanistic model's under the same control (2.27 %), so it is adequate by what the data
    measured; metrics.json, the report and what ``ude-fit fit`` prints carry both
    yardsticks (without the control nothing of this is there:
    tests/test_ude_invasive_cbc.py)."""
    r = fits["loose+control"][0]
    doc = r.to_json()
    (rec,) = doc["starts"]["records"]
    c = rec["controlled"]
    assert c["missed"] == 0 and rec["metrics"]["missed"] == 0
    assert c["judged"] == {"branch_rms": c["branch_rms"], "branch_max": c["branch_max"],
                           "missed": 0}
    assert rec["metrics"]["branch_rms"] >= 5 * c["branch_rms"], rec
    assert r.starts[0].judged.summary.branch_rms == pytest.approx(c["branch_rms"])
    mech = doc["mechanistic"]["controlled"]
    assert mech["judged"]["branch_rms"] >= 10 * c["branch_rms"], (mech, c)
    assert len(mech["errors"]) == len(mech["amplitudes"]) == doc["data"]["points"]
    assert rec["adequate"] and doc["ude"]["controlled"]["judged"] == c["judged"]
    assert doc["starts"]["criterion"]["judged_by"] == "the orbits under the recorded control"
    from ude_fit.report.markdown import render
    text = render({**doc, "version": "test", "written": "now", "command": "fit",
                   "options": r.options.to_json()}, {})
    assert "| orbits under the recorded control: amplitude error, RMS |" in text
    assert "judged under the control: RMS, missed |" in text
    from ude_fit.cli.fit import summary
    said = summary(r, 1)
    assert said[1] == (f"judged under the recorded control: mechanistic "
                        f"{100 * mech['judged']['branch_rms']:.2f} % (0 missed), UDE "
                        f"{100 * c['branch_rms']:.2f} % (0 missed)"), said


def test_the_control_is_reported_against_the_heave_spring(fits):
    """Every invasively held point's control force against the heave spring's, |u1| / (k_h
    |h1|): the rig records its control as the force itself, so with the rig's own k_h this
    is known exactly; the fit's figure (k_h identified with the control) is within 10 % of
    it (the quasi-steady identification puts k_h 4 % low), and every point is at least
    0.1 % (measured 0.24-2.6 %; the same ratio on the campaign held on the truth is at
    most 0.015 %). The report has the column."""
    r = fits["loose+control"][0]
    doc = r.to_json()
    points = doc["data"]["point_records"]
    ratios = doc["mechanistic"]["identification"]["control"]["against_heave_stiffness"]
    amplitudes = [p["measured"] for p in doc["mechanistic"]["points"]]
    assert len(ratios) == len(points) == len(amplitudes) > 0
    for point, ratio, a in zip(points, ratios, amplitudes):
        truth = point["holding"]["control_amplitude"] / (FLUTTER_NOMINAL["k_h"] * a)
        assert ratio == pytest.approx(truth, rel=0.1), point["source"]
        assert ratio > 1e-3, point["source"]
    from ude_fit.report.markdown import render
    text = render({**doc, "version": "test", "written": "now", "command": "fit",
                   "options": r.options.to_json()}, {})
    assert "against the heave spring |" in text


def test_the_fit_says_where_the_invasive_points_lie_and_that_a_branch_is_one_sided(fits):
    """The invasive campaign's targets alternate 5 % above and below point by point, each
    airspeed's unstable point first and the top two airspeeds stable only: every unstable
    point is held above its open-loop orbit (6-16 % above the truth's amplitude), the
    stable ones below (about 3 %) but the one at 24 m/s, above. Against the kept UDE's
    open-loop orbits (measured: 2-5 % above the truth's on the unstable branch, within
    0.7 % on the stable one) every invasive point keeps its side, so the fit records the
    unstable branch as held on one side, not the stable one, and the report and what
    ``ude-fit fit`` prints tell the user to hold two targets per airspeed."""
    from ude_fit.analysis.controlled import HeldSides
    from ude_fit.report.markdown import render
    r = fits["loose+control"][0]
    doc = r.to_json()
    labels = [p["stable"] for p in doc["data"]["point_records"]]
    sides = doc["ude"]["controlled"]["held_sides"]
    assert sides == {"above": {"stable": 1, "unstable": labels.count(False)},
                     "below": {"stable": labels.count(True) - 1, "unstable": 0},
                     "one_sided": ["unstable"]}
    text = render({**doc, "version": "test", "written": "now", "command": "fit",
                   "options": r.options.to_json()}, {})
    warning = HeldSides(sides["above"], sides["below"]).warning()
    assert "hold each airspeed at two targets" in warning and warning in text
    from ude_fit.cli.fit import summary
    assert summary(r, 1)[-1] == warning
    balanced = HeldSides({"stable": 2, "unstable": 1}, {"stable": 1, "unstable": 0})
    assert balanced.one_sided == () and balanced.warning() is None
    with pytest.raises(ValueError, match="held sides"):
        HeldSides({"stable": -1, "unstable": 0}, {"stable": 0, "unstable": 0})


def test_the_spring_ratio_of_a_lee2020_record(tmp_path):
    """A lee2020-format record with a 4 mV control at the orbit's frequency: the ratio is
    the gain times 4 mV over k_h times the heave's first-harmonic amplitude, exactly (the
    gain's sign does not matter: a magnitude against a magnitude)."""
    write_lee(tmp_path / "CBC_v1.mat", control=4e-3)
    ds = load(tmp_path, "flutter")
    (ratio,) = against_heave_stiffness(ds, -2500.0, 3500.0)
    assert ratio == pytest.approx(2500.0 * 4e-3 / (3500.0 * ds.orbits[0].amplitude), rel=1e-6)



# ---- the wake added to the mechanistic model (--add): the mechanistic stage alone ----

WAKE = (("heave_unsteady_aero", None), ("pitch_unsteady_aero", None))


@pytest.fixture(scope="module")
def wake(tmp_path_factory):
    """The three fits' mechanistic stage with the wake's lag added (`--add
    heave_unsteady_aero pitch_unsteady_aero`), judged against the open-loop truth."""
    folder = tmp_path_factory.mktemp("wake")
    cases, truth = mechanistic_cases(folder, LOOSE, WAKE)
    return folder, cases, truth


def test_with_the_wake_added_the_control_input_recovers_the_non_invasive_fit(wake):
    """Issue 17's invasive criterion, at the mechanistic model: with the lag the
    quasi-steady model lacks added as a term of its own, the invasive campaign fitted with
    the control as an input has its Hopf point and fold within 0.1 m/s of the non-invasive
    campaign's fit and an error against the open-loop truth at most 1.5 times that one's
    (measured 0.018 and 0.060 m/s; 0.002 % against 0.040 %). Without the control the same
    model is measurably worse (measured 1.79 %, its fold 0.64 m/s late). The identification
    names the effects and where their coefficients came from."""
    held, with_u, without = (wake[1][name][0].to_json()
                             for name in ("held", "loose+control", "loose"))
    assert held["missed"] == with_u["missed"] == without["missed"] == 0
    said = criterion(*(criterion_figures(m) for m in (held, with_u, without)))
    assert said["met"], said
    assert said["without_control_ratio"] >= 10, said
    assert abs(without["fold"]["model"] - held["fold"]["model"]) >= 0.3, (without, held)
    ident = wake[1]["loose+control"][1]
    assert [e["key"] for e in ident["effects"]] == [k for k, _ in WAKE]
    assert ident["control"]["gain"] == 1.0
    added = {n: src for n, src in ident["sources"].items() if "_unsteady_aero[" in n}
    assert len(added) == 10
    assert set(added.values()) == {"identified from the orbits (least squares)"}


# ---- the loop with the control as an input: it finds the wake itself ----

@pytest.fixture(scope="module")
def loops(wake):
    """The discovery loop (``ude-fit loop``, the pipeline's second part) on the campaigns
    of the wake fixture, judged against the open-loop truth: on the non-invasive campaign,
    on the invasive one with the control as an input, and on it without."""
    from tests.invasive_cases import loop_cases
    folder, _, truth = wake
    return {name: (res, m) for name, (res, _, m) in loop_cases(folder, truth).items()}


def test_the_loop_with_the_control_input_recovers_the_non_invasive_loop(loops):
    """Issue 17's invasive criterion at the loop's refined model, with no effect named by
    us: on the design rig the quasi-steady model lacks the wake's lag. Both loops add an
    aerodynamic effect first, and with the control as an input the refined model's Hopf
    point and fold are within 0.1 m/s of the loop's on the non-invasive campaign, its error
    against the open-loop truth at most 1.5 times that one's (measured: the Jones wake in
    heave first both times, then with the control a pitch lag and a pitch-heave coupling;
    0.017 and 0.061 m/s apart, 0.002 % against 0.039 %). Without the control
    the loop reads the control's force as physics: 10 times the error or more, the fold
    0.3 m/s or more away (measured 1.78 %, 0.64 m/s)."""
    held, with_u, without = (loops[n][1] for n in ("held", "loose+control", "loose"))
    assert held["missed"] == with_u["missed"] == without["missed"] == 0
    from ude_fit.models.library import AERO, effect
    for name in ("held", "loose+control"):
        added = loops[name][0].added
        assert added and effect("flutter", added[0][0]).kind == AERO, loops[name][0].steps
    said = criterion(*(criterion_figures(m) for m in (held, with_u, without)))
    assert said["met"], said
    assert said["without_control_ratio"] >= 10, said
    assert abs(without["fold"]["model"] - held["fold"]["model"]) >= 0.3, (without, held)


def test_the_loop_judges_the_orbits_under_the_recorded_control(loops):
    """With the control as an input the loop's rule compares each model's orbits under the
    recorded control with the points, not its open-loop diagram: the refined model, right
    about the rig, meets every invasively held point under its control (amplitude error
    below 0.05 %), while its open-loop diagram is 10 times as far from them or more (the
    points lie off the open-loop orbits by what the control did); the quasi-steady model
    is at least 10 times as far as the refined one under the control."""
    res = loops["loose+control"][0]
    before, after = res.before, res.after
    assert after.controlled.missed == 0 and after.controlled.branch_rms < 5e-4
    assert after.metrics.summary.branch_rms >= 10 * after.controlled.branch_rms
    assert before.controlled.branch_rms >= 10 * after.controlled.branch_rms
    assert after.metrics.summary.missed == 0 and after.judged.missed == 0
    assert after.judged.branch_rms == pytest.approx(after.controlled.branch_rms)
    assert loops["loose"][0].after.controlled is None
    assert loops["loose"][0].after.judged is loops["loose"][0].after.metrics.summary


def test_the_loop_records_the_control_and_its_reports_say_so(loops, tmp_path):
    """Every model of the controlled loop records the gain and where it came from (the
    rig's control is a force: 1), the open-loop loop records none, and the loop's report
    says the control was a known input."""
    from ude_fit.discovery.loop import metrics_document
    from ude_fit.report.loop_markdown import render_loop
    res = loops["loose+control"][0]
    for stage in (res.before, res.after):
        assert stage.identification["control"]["gain"] == 1.0
        assert stage.identification["control"]["unit"] == "N"
    assert "control" not in loops["loose"][0].before.identification
    doc = {**metrics_document(res), "command_name": "loop", "version": "test",
           "written": "now", "command": "ude-fit loop", "data": {"points": 7, "sources": []}}
    text = render_loop(doc, {})
    assert "The recorded holding control is a known heave force" in text
    assert "gain 1 N per N" in text
    assert "orbits under the recorded control: amplitude error, RMS" in text
    assert doc["after"]["controlled"]["missed"] == 0
    assert "controlled" in doc["steps"][0]["metrics"]


def test_the_pipeline_hands_its_loop_the_control(wake, monkeypatch):
    """``ude-fit pipeline --control-input``: the loop takes the control as the fit does
    (the fit's training is not what this checks and is skipped)."""
    import ude_fit.pipeline as P
    from ude_fit.training.options import FitOptions
    monkeypatch.setattr(P, "fit", lambda ds, opts, progress=None: None)
    opts = P.PipelineOptions(FitOptions("flutter", control_input=True), bootstrap=20,
                             max_effects=1)
    assert opts.loop_json()["control_input"] is True
    result = P.run_pipeline(load([wake[0] / "loose.h5"], "flutter"), opts)
    assert result.loop.control is not None
    assert result.loop.before.identification["control"]["gain"] == 1.0
