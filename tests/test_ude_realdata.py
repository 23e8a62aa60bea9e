"""Real-data deliverables of issue 17: stability labels from the lab's file names and from the
user's explicit rules, the mechanistic model identified with physical signs (never another
rig's values) or taken from the user's parameter file, and how invasive the holding
control was at every point.

Truth: small lee2020-format files written by the tests with known signals; renamed copies
of the real lee2020 files (in tmp_path only); a campaign of the rig's own orbits with a
planted negative heave damping (a plugin force), for which unconstrained least squares
must give a negative damping.
"""

from __future__ import annotations

import math
import shutil

import numpy as np
import pytest
import scipy.io

from tests import ude_fixtures as F
from ude_fit import cli
from ude_fit.data import DataError, StabilityLabels, load
from ude_fit.data.holding import SIGNIFICANCE, measure_holding
from ude_fit.training.options import FitOptions

import jax  # noqa: E402  (after the imports above, before any array)

jax.config.update("jax_enable_x64", True)

RATE = 5000.0
FREQ = 2.4


def write_lee(path, *, V=20.0, n=20000, control=0.0, target_gain=1.0, noise=0.0, seed=0,
              pitch_offset=0.35):
    """A lee2020-format file: heave (row 0, volts about 3.3 V), target (row 1), control
    (row 2: a cosine of amplitude ``control`` V at the orbit's frequency plus white noise
    of RMS ``noise``), pitch (row 3, rad: 0.05 rad about ``pitch_offset``, 1 rad behind the
    heave, wrapped at 2 pi as the encoder reads it), a constant row 4."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / RATE
    ph = 2 * np.pi * FREQ * t
    heave = 3.3 + 0.2 * np.cos(ph)
    data = np.vstack([heave, 3.3 + target_gain * 0.2 * np.cos(ph),
                      control * np.cos(ph + 0.3) + noise * rng.standard_normal(n),
                      np.mod(pitch_offset + 0.05 * np.cos(ph + 1.0), 2 * np.pi),
                      np.full(n, 3.3)])
    scipy.io.savemat(str(path), {"data": data, "time": t[None, :], "Wind_sped": V,
                                 "freq_actual": FREQ})


@pytest.fixture
def named(tmp_path):
    for i, name in enumerate(("CBC_stable_v20_0", "CBC_unstable_v21_0", "CBC_v22_0",
                              "run_23_0")):
        write_lee(tmp_path / f"{name}.mat", V=20.0 + i)
    return tmp_path


# ---- stability labels -------------------------------------------------------------------

def test_stability_from_the_lab_names(named):
    ds = load(named, "flutter")
    labels = {o.source.rsplit("/", 1)[-1]: (o.stable, o.stability_from) for o in ds}
    assert labels == {"CBC_stable_v20_0.mat": (True, "file name"),
                      "CBC_unstable_v21_0.mat": (False, "file name"),
                      "CBC_v22_0.mat": (False, "file name"),
                      "run_23_0.mat": (None, "")}
    assert [s.rsplit("/", 1)[-1] for s in ds.unknown_stability()] == ["run_23_0.mat"]
    rec = {r["source"].rsplit("/", 1)[-1]: r for r in ds.point_records()}
    assert rec["run_23_0.mat"]["stability_from"] == "unknown"


def test_stability_rules_win_over_the_names(named):
    ds = load(named, "flutter", StabilityLabels.parse(["run_*=stable,CBC_v22*=stable"]))
    by = {o.source.rsplit("/", 1)[-1]: o for o in ds}
    assert by["run_23_0.mat"].stable is True
    assert by["CBC_v22_0.mat"].stable is True
    assert by["CBC_v22_0.mat"].stability_from == "--stability CBC_v22*=stable"
    assert by["CBC_unstable_v21_0.mat"].stable is False       # untouched: no rule matched
    assert ds.unknown_stability() == []


@pytest.mark.parametrize("specs, message", [
    (["run_*"], "expected GLOB=stable"),
    (["run_*=maybe"], "must be stable or unstable"),
    (["=stable"], "expected GLOB=stable"),
])
def test_bad_stability_rules_are_one_line_errors(specs, message):
    with pytest.raises(ValueError, match=message):
        StabilityLabels.parse(specs)


@pytest.mark.parametrize("spec, message", [
    ("nothing_*=stable", "matches no loaded point"),
    ("run_*=stable,run_23*=unstable", "rules disagree"),
])
def test_stability_rules_that_cannot_be_meant_are_refused(named, spec, message):
    with pytest.raises(DataError, match=message):
        load(named, "flutter", StabilityLabels.parse([spec]))


@pytest.mark.parametrize("flag, name, content, message", [
    ("--stability", None, "run_*=maybe", "must be stable or unstable"),
    ("--stability", None, "nothing*=stable", "matches no loaded point"),
    ("--mechanistic-params", "p.toml", "c_h = -1.0\n", "c_h must be positive"),
    ("--mechanistic-params", "p.toml", "c_hh = 1.0\n", "'c_hh' is not a parameter"),
    ("--mechanistic-params", "p.toml", "k_h = \"stiff\"\n", "k_h must be a finite number"),
    ("--mechanistic-params", "p.toml", "k_h = [\n", "not a TOML file"),
])
def test_bad_option_files_are_one_line_errors_and_write_nothing(named, tmp_path, capsys, flag,
                                                                name, content, message):
    value = content
    if name is not None:
        (tmp_path / name).write_text(content)
        value = str(tmp_path / name)
    out = tmp_path / "out"
    rc = cli.main(["fit", str(named), "--system", "flutter", flag, value, "--out", str(out),
                   "--quiet"])
    err = capsys.readouterr().err
    assert rc == 2 and message in err and len(err.strip().splitlines()) == 1, err
    assert not out.exists()


def test_renamed_lee2020_files_keep_their_stability(lee2020_dir, tmp_path):
    """The other configuration's files are named CBC_unstable_v...: copies of the real
    files under such names (in tmp_path only) read as unstable; an unlabelled name is
    unknown, and a rule labels it."""
    src = lee2020_dir / "model2"
    shutil.copy(src / "CBC_v25_8.mat", tmp_path / "CBC_unstable_v25_8.mat")
    shutil.copy(src / "CBC_stable_v23_2.mat", tmp_path / "point_v23_2.mat")
    ds = load(tmp_path, "flutter")
    by = {o.source.rsplit("/", 1)[-1]: o.stable for o in ds}
    assert by == {"CBC_unstable_v25_8.mat": False, "point_v23_2.mat": None}
    ds = load(tmp_path, "flutter", StabilityLabels.parse(["point_*=stable"]))
    assert {o.stable for o in ds} == {True, False}


# ---- invasive control ------------------------------------------------------------------

def test_holding_figures_against_known_signals(tmp_path):
    """A control cosine of known amplitude in known white noise: the amplitude comes back
    within a few standard errors, the standard error is the noise's sigma sqrt(2/N), and
    a control of pure noise is not invasive; the target 10 % above the response gives a
    10 % mismatch."""
    n, sigma = 20000, 2e-3
    write_lee(tmp_path / "CBC_v1.mat", n=n, control=5e-4, noise=sigma, target_gain=1.1)
    write_lee(tmp_path / "CBC_v2.mat", V=21.0, n=n, control=0.0, noise=sigma, seed=1)
    held, quiet = (o.holding for o in load(tmp_path, "flutter"))
    se = sigma * math.sqrt(2.0 / n)
    assert held.control_unit == "V"
    assert held.control_standard_error == pytest.approx(se, rel=0.05)
    assert abs(held.control_amplitude - 5e-4) < 4 * se
    assert held.invasive and held.significance > SIGNIFICANCE
    assert held.target_mismatch == pytest.approx(0.1, rel=1e-6)
    assert not quiet.invasive and quiet.target_mismatch == pytest.approx(0.0, abs=1e-9)


def test_holding_relative_to_the_gains_is_the_mismatch_for_a_pd_law():
    """For u = kp (T - x) + kd (T' - x') the control's fundamental over the gains times
    the response's is exactly |T1 - X1| / |X1|: the two figures agree."""
    w = 2 * np.pi * 3.0
    t = np.arange(4000) / 1000.0
    x = 0.01 * np.cos(w * t)
    T = 0.012 * np.cos(w * t + 0.2)
    kp, kd = 300.0, 5.0
    u = kp * (T - x) + kd * (-0.012 * w * np.sin(w * t + 0.2) + 0.01 * w * np.sin(w * t))
    h = measure_holding(w * t, x, T, u, "N", gains=(kp, kd), omega=w)
    assert h.control_relative_to_gains == pytest.approx(h.target_mismatch, rel=1e-9)
    assert h.target_mismatch == pytest.approx(abs(0.012 * np.exp(0.2j) - 0.01) / 0.01,
                                              rel=1e-9)


def test_lee2020_control_is_measured_at_every_point(lee2020_dir):
    """The issue's own figure: on lee2020 the control's first harmonic is 1.5-5.6 mV at
    every point, stable ones included; each is far above its channel's noise."""
    ds = load(lee2020_dir / "model2", "flutter")
    amps = np.array([o.holding.control_amplitude for o in ds])
    assert np.all((amps > 1.4e-3) & (amps < 5.7e-3)), amps
    assert all(o.holding.invasive for o in ds)
    assert all(0 <= o.holding.target_mismatch < 0.2 for o in ds)


# ---- the mechanistic model from the data ---------------------------------------------

NEGATIVE_DAMPING = '''import numpy as np


def force(t, q, qdot, params):
    return np.array([20.0 * qdot[0], 0.0])
'''


@pytest.fixture(scope="module")
def negative_damping(tmp_path_factory):
    """A campaign of the rig's true orbits with 20 N s/m of negative heave damping added
    (a plugin force): the design heave damping is 15.4 N s/m, so the truth's is negative
    and unconstrained least squares says so."""
    tmp = tmp_path_factory.mktemp("negdamp")
    plug = tmp / "negative_damping.py"
    plug.write_text(NEGATIVE_DAMPING)
    path = tmp / "negdamp.h5"
    F.write_truth_campaign(path, "flutter", airspeeds=(12.0, 14.0, 16.0, 18.0),
                           plugin=f"{plug}:force")
    return load(path, "flutter")


def test_negative_least_squares_damping_is_bounded_not_replaced(negative_damping):
    from ude_fit.analysis.diagram import _evaluate
    from ude_fit.fitting import prepare
    from ude_fit.mechanistic_stage import identify_mechanistic
    from ude_fit.models.ude import UDE

    _, data, ranges, ref, src = prepare(negative_damping, "flutter", None, 32)
    mech, ident = identify_mechanistic(data, "flutter")
    assert ident["at_bound"] == ["c_h"] and ident["unconstrained"]["c_h"] < -1.0
    assert all(v >= 0 for k, v in ident["parameters"].items()
               if k in ("c_h", "c_alpha", "k_h", "k_alpha"))
    assert "design" not in ident["method"]
    assert "physical bound 0" in ident["sources"]["c_h"]
    assert ident["sources"]["k_h"] == "identified from the orbits (least squares)"
    assert ident["sources"]["m_T"] == "known geometry (design value)"
    assert mech.unphysical() == ""
    scales = np.asarray(data.y_scale)
    _, m = _evaluate(UDE(mech), negative_damping, ranges, scales, ref, src)
    # the old fall-back, the simulated rig's design values (no negative damping at all)
    _, design = _evaluate(UDE(mech.nominal()), negative_damping, ranges, scales, ref, src)
    assert m.hopf.model is not None, m
    assert (design.hopf.model is None
            or abs(m.hopf.error) < abs(design.hopf.error)), (m, design)
    assert m.summary.missed < len(negative_damping), m
    assert m.summary.missed <= design.summary.missed, (m, design)


def test_parameter_file_values_are_used_and_said_so(negative_damping, tmp_path):
    from ude_fit.fitting import prepare
    from ude_fit.mechanistic_stage import identify_mechanistic
    from ude_fit.models.parameter_file import MechanisticParameters

    p = tmp_path / "rig.toml"
    p.write_text("c_h = 2.5\nm_T = 17.0\n")
    given = MechanisticParameters.read(p, "flutter")
    _, data, *_ = prepare(negative_damping, "flutter", None, 32)
    mech, ident = identify_mechanistic(data, "flutter", given=given)
    assert float(mech.c_h) == 2.5 and float(mech.m_T) == 17.0
    assert ident["sources"]["c_h"] == ident["sources"]["m_T"] == f"user file {p}"
    assert ident["sources"]["k_h"].startswith("identified from the orbits")
    assert "c_h" not in ident["std_error"]


def test_report_lists_unknown_points_holding_and_parameter_sources(named):
    """report.md from a metrics document: the unknown-stability point by file, the holding
    table with every point's figures, and where each mechanistic parameter came from."""
    from ude_fit.report.markdown import render

    from ude_fit.training.sensor_zero import with_sensor_zero

    ds = with_sensor_zero(load(named, "flutter"), zero="identified")
    zero = ds.sensor_zero.to_json()
    metrics = {
        "system": "flutter", "version": "test", "written": "now", "command": "ude-fit fit",
        "approximator": "nn", "training": "periodic", "ude": None,
        "data": {"points": len(ds), "stable": 1, "unstable": 2, "sources": list(ds.sources),
                 "max_amplitude": float(ds.amplitudes().max()),
                 "unknown_stability": ds.unknown_stability(), "sensor_zero": zero,
                 "point_records": ds.point_records()},
        "mechanistic": {"branch_rms": None, "branch_max": None, "missed": 4,
                        "trajectory_rms": None, "hopf": None, "fold": None, "points": [],
                        "parameters": {"c_h": 0.0}, "std_error": {"c_h": 0.1},
                        "identification": {
                            "method": "equation error (bounded)", "known": {"m_T": 16.9},
                            "sources": {"c_h": "identified from the orbits, at its physical "
                                               "bound 0", "m_T": "user file rig.toml"}}},
        "starts": {"requested": 1, "adequate": 0, "completed": 0, "dropped": [],
                   "records": [], "criterion": {"factor_of_best": 2.0, "floor": 0.01,
                                                "data_scatter": None}},
    }
    text = render(metrics, {})
    unknown = ds.unknown_stability()[0]
    assert "1 point(s) of unknown stability" in text and f"`{unknown}`" in text
    assert "stability checks (training and the adequacy test) skip them" in text
    table = text[text.index("### Holding control"):]
    assert all(f"`{o.source}`" in table for o in ds)
    assert "| c_h | 0 | 0.1 | identified from the orbits, at its physical bound 0 |" in text
    assert "| m_T | 16.9 | — | user file rig.toml |" in text
    assert zero["identified"] and zero["points"] == len(ds)
    assert (f"The files of {len(ds)} point(s) do not record the sensors' zero" in text
            and f"alpha {zero['offsets'][1]:.5g} ±" in text and "zero-lift incidence" in text)


def _lee_with_pitch(path, failed_of_phase, pitch_offset=0.35):
    """write_lee's file with the encoder's failed reads (its all-ones code) where
    failed_of_phase(ph) is true; the loaded orbit."""
    from ude_fit.data.lee import LEE_PITCH_INVALID
    write_lee(path, V=21.0, pitch_offset=pitch_offset)
    m = scipy.io.loadmat(str(path))
    data = m["data"].copy()
    ph = 2 * np.pi * FREQ * np.arange(data.shape[1]) / RATE
    data[3, failed_of_phase(ph)] = LEE_PITCH_INVALID + 1e-6
    scipy.io.savemat(str(path), {**{k: v for k, v in m.items() if not k.startswith("__")},
                                 "data": data})
    return load([path], "flutter")[0]


def _assert_the_written_swing(o, offset=0.35):
    """The pitch as write_lee writes it: mean 0, 0.05 rad, 1 rad behind the heave, nothing
    else; its mean in the encoder's frame the written ``offset``."""
    pitch = o.coeffs[1]
    K = (pitch.size - 1) // 2
    assert abs(pitch[0]) < 1e-6                       # the signal's mean is its offset
    assert not o.zero_known and o.sensor_means[1] == pytest.approx(offset, abs=1e-6)
    assert math.hypot(pitch[1], pitch[1 + K]) == pytest.approx(0.05, rel=1e-6)
    assert math.atan2(-pitch[1 + K], pitch[1]) == pytest.approx(1.0, abs=1e-6)
    assert np.all(np.abs(pitch[2:1 + K]) < 1e-6) and np.all(np.abs(pitch[2 + K:]) < 1e-6)


def test_pitch_mean_is_the_fitted_mean_where_failed_reads_cluster(tmp_path):
    """The encoder's failed reads (the all-ones code) come in bursts at a few angles of the
    cycle. Left out, they leave the valid samples' plain mean off the signal's own mean, by
    where they fall; the pitch's mean is the fitted one, so the loaded orbit is the signal
    with its mean removed and its harmonics as they were."""
    # 20 % of the reads fail, all near the top of the pitch's swing
    o = _lee_with_pitch(tmp_path / "CBC_v21_0.mat",
                        lambda ph: np.cos(ph + 1.0) > np.quantile(np.cos(ph + 1.0), 0.8))
    _assert_the_written_swing(o)


@pytest.mark.parametrize("offset", [0.01, 2 * math.pi - 0.01])
def test_a_pitch_wrapped_at_2pi_is_unwrapped(tmp_path, offset):
    """The data's README: the pitch row is wrapped at 2 pi and offset. The lee2020 files'
    offset keeps it clear of the wrap, another configuration's need not: a pitch swinging
    across 0 = 2 pi (its readings jumping between near 0 and near 2 pi), with bursts of the
    encoder's failed reads among them, loads as the swing itself."""
    def bursts(ph):
        failed = np.zeros(ph.size, dtype=bool)
        for start in np.random.default_rng(1).integers(0, ph.size - 15, 40):
            failed[start:start + 15] = True
        return failed

    path = tmp_path / "CBC_v21_0.mat"
    o = _lee_with_pitch(path, bursts, pitch_offset=offset)
    row = scipy.io.loadmat(str(path))["data"][3]
    assert np.ptp(row[row < 2 * np.pi - 1e-3]) > 6.0    # the valid readings do wrap
    _assert_the_written_swing(o, offset)
    assert o.noise[1] < 1e-6 * 0.05


def test_own_means_keep_each_points_mean_and_say_so(named):
    """With ``--sensor-zero own-means`` the orbits stay about their own means, as loaded,
    and the record (metrics.json, the report) says which zero was used."""
    from ude_fit.report.format import sensor_zero_lines
    from ude_fit.training.sensor_zero import with_sensor_zero

    ds = load(named, "flutter")
    kept = with_sensor_zero(ds)
    assert all(np.array_equal(a.coeffs, b.coeffs) for a, b in zip(ds, kept))
    z = kept.sensor_zero.to_json()
    assert not z["identified"] and z["points"] == len(ds) and z["offsets"] == [None, None]
    assert "each point's own mean" in " ".join(sensor_zero_lines({"sensor_zero": z}))
    with pytest.raises(ValueError, match="own-means or identified"):
        with_sensor_zero(ds, zero="guessed")
    with pytest.raises(ValueError, match="--sensor-zero must be auto, own-means, identified"):
        FitOptions(system="flutter", sensor_zero="guessed")


def test_lee2020_keeps_its_own_means_where_the_identified_zero_does_not_help(lee2020_dir):
    """``auto`` on the real points: the mechanistic model misses all 11 with the identified
    zero as with each point's own mean, so the identified zero has not shown it is placed
    right, and each point keeps its own mean: the orbits exactly as loaded. The report
    says which zero and why."""
    from ude_fit.mechanistic_stage import with_chosen_zero
    from ude_fit.report.format import sensor_zero_lines

    ds = load(lee2020_dir / "model2", "flutter")
    chosen = with_chosen_zero(ds, FitOptions(system="flutter"))
    assert all(np.array_equal(a.coeffs, b.coeffs) for a, b in zip(ds, chosen))
    z = chosen.sensor_zero.to_json()
    assert not z["identified"] and z["points"] == 11
    assert z["judged"] == {"own-means": {"missed": 11, "branch_rms": None},
                           "identified": {"missed": 11, "branch_rms": None}}
    line = " ".join(sensor_zero_lines({"sensor_zero": z}))
    assert "each point's own mean" in line and "no better" in line
