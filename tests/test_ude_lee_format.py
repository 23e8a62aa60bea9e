"""Wind-tunnel files from a rig configuration nothing was tuned on (tests/lee_format.py):
the simulated aerofoil, in another configuration, held on its true orbits and written in the
lee2020 layout (heave in sensor volts about an offset, pitch about an encoder offset with
bursts of failed reads, the actuator in volts, the lab's file names).

Truth: the configured rig's own orbits (airspeed, stability, heave amplitude). The default
fit on such files, against the rig's Hopf and fold, is a benchmark
(benchmarks/unseen_configuration_benchmark.py): it takes minutes per start.
"""

from __future__ import annotations

import jax
import numpy as np
import pytest

jax.config.update("jax_enable_x64", True)       # ude_fit identifies and traces in float64

from tests.lee_format import (HEAVE_M_PER_V, HEAVE_OFFSET_V, PITCH_OFFSET_RAD,  # noqa: E402
                               point_airspeeds, truth_of, write_lee_campaign)
from benchmarks.unseen_configuration_benchmark import truth_on_points  # noqa: E402
from ude_fit.data import load
from ude_fit.fitting import prepare
from ude_fit.mechanistic_stage import identify_mechanistic, with_chosen_zero
from ude_fit.training.options import FitOptions
from ude_fit.training.sensor_zero import ZeroJudgement, with_sensor_zero

PHYSICS = ("k_alpha=70", "k_h=3600", "c_h=10")      # the benchmark's "stiff" configuration


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    folder = tmp_path_factory.mktemp("lee_format")
    truth = write_lee_campaign(folder, PHYSICS, sigma=0.02, seed=0, n_speeds=3, n_stable=2,
                               record_s=4.0)
    return folder, truth


def test_the_configured_rig_is_another_rig():
    design, other = truth_of(()), truth_of(PHYSICS)
    assert abs(other["hopf"] - design["hopf"]) > 1.0
    assert abs(other["fold"] - design["fold"]) > 1.0
    speeds = point_airspeeds(other["hopf"], other["fold"], 7)
    assert other["fold"] < speeds.min() and speeds.max() < other["hopf"]


def test_every_point_loads_with_its_stability_and_its_true_amplitude(written):
    folder, truth = written
    ds = load(folder, "flutter")
    by_name = {o.source.rsplit("/", 1)[-1]: o for o in ds}
    assert sorted(by_name) == sorted(p["file"] for p in truth["points"])
    assert len(truth["points"]) == 5            # 3 unstable, 2 stable
    assert ds.unknown_stability() == []
    for p in truth["points"]:
        o = by_name[p["file"]]
        assert o.stable is p["stable"] and o.stability_from == "file name"
        assert o.parameter == pytest.approx(p["airspeed"])
        # the offsets, the volts and the failed pitch reads are the layout's: the heave's
        # first harmonic is the true orbit's, to the noise's few per cent
        assert o.amplitude == pytest.approx(p["amplitude"], rel=0.05), p
        assert np.all(np.isfinite(o.coeffs)) and not o.zero_known


def test_the_sensors_zero_is_identified_and_the_stiffness_with_it(written):
    """The files do not record the heave sensor's DC level nor the encoder's zero. Taken
    about the rig's rest position identified from the points, the orbits give the configured
    rig's pitch stiffness (70, 774.7, 3490.7; the quasi-steady model's error is the wake's
    lag); taken each about its own mean, the quadratic stiffness's pull on a large orbit's
    mean is lost and the identification mistakes it (``--sensor-zero own-means``)."""
    folder, _ = written
    ds = load(folder, "flutter")
    zeroed = with_sensor_zero(ds, zero="identified")
    z = zeroed.sensor_zero
    assert z.identified and z.points == len(ds) and not zeroed.zero_unknown().any()
    assert z.offsets[0] == pytest.approx(HEAVE_OFFSET_V * HEAVE_M_PER_V, abs=5e-4)
    assert z.offsets[1] == pytest.approx(PITCH_OFFSET_RAD, abs=1e-3)
    assert z.error < 0.2 * z.error_own_means

    def pitch_stiffness(dataset):
        _, data, *_ = prepare(dataset, "flutter", None, 32)
        p = identify_mechanistic(data, "flutter")[1]["parameters"]
        return np.array([p["k_alpha"], p["k_alpha2"], p["k_alpha3"]])

    truth = np.array([70.0, 774.7, 3490.7])
    np.testing.assert_allclose(pitch_stiffness(zeroed), truth, rtol=0.03)
    assert abs(pitch_stiffness(with_sensor_zero(ds))[0] / truth[0] - 1) > 0.2


def test_the_default_takes_the_identified_zero_where_the_model_meets_the_points_with_it(
        written):
    """``auto`` (the default): with each point's own mean the mechanistic model misses
    points of this rig's diagram; with the identified zero it meets them all, so the fit
    takes the identified zero, and the record says why, with both diagrams' figures."""
    folder, _ = written
    ds = load(folder, "flutter")
    chosen = with_chosen_zero(ds, FitOptions(system="flutter"))
    z = chosen.sensor_zero
    assert z.identified and not chosen.zero_unknown().any()
    assert z.judged["identified"].missed == 0 < z.judged["own-means"].missed
    assert "chosen (auto)" in z.method and "better" in z.method
    assert z.to_json()["judged"]["identified"] == {"missed": 0,
                                                    "branch_rms": z.judged["identified"].branch_rms}
    with pytest.raises(ValueError, match="count of points"):
        ZeroJudgement(-1, None)
    identified = with_sensor_zero(ds, zero="identified")
    assert all(np.array_equal(a.coeffs, b.coeffs) for a, b in zip(chosen, identified))
    # a zero chosen once is not chosen again (the pipeline's loop sees the fit's)
    assert with_chosen_zero(chosen, FitOptions(system="flutter")) is chosen


def _loop(folder, out, *flags):
    """``ude-fit loop`` as a user runs it (a subprocess), its metrics.json and report."""
    import json
    import subprocess
    import sys
    r = subprocess.run([sys.executable, "-m", "ude_fit.cli", "loop", str(folder),
                        "--system", "flutter", "--bootstrap", "10", "--quiet",
                        "--out", str(out), *flags], capture_output=True, text=True,
                       timeout=600)
    assert r.returncode == 0, r.stderr
    return json.loads((out / "metrics.json").read_text()), (out / "report.md").read_text()


def test_the_loop_starts_from_the_zero_a_fit_would_choose_and_names_the_wake(written,
                                                                           tmp_path):
    """``ude-fit loop`` chooses the sensors' zero as the fit does: on this rig's files it
    takes the identified zero, its mechanistic model meets every point, and the effect it
    adds is what the rig has beyond that model, the wake's lag in heave, which brings the
    diagram to the points. About each point's own mean (``--sensor-zero own-means``) its
    mechanistic model misses points, which no quasi-steady term it could add puts back."""
    folder, _ = written
    doc, report = _loop(folder, tmp_path / "auto")
    zero = doc["data"]["sensor_zero"]
    assert zero["identified"] and "chosen (auto)" in zero["method"]
    assert zero["judged"]["identified"]["missed"] == 0 < zero["judged"]["own-means"]["missed"]
    assert "do not record the sensors' zero" in report and "chosen (auto)" in report
    assert doc["before"]["missed"] == 0
    assert doc["effect"]["key"] == "heave_unsteady_aero"
    assert doc["after"]["missed"] == 0
    assert doc["after"]["branch_rms"] < 0.5 * doc["before"]["branch_rms"]

    own, _ = _loop(folder, tmp_path / "own", "--sensor-zero", "own-means")
    assert not own["data"]["sensor_zero"]["identified"]
    assert own["before"]["missed"] > 0 and own["after"]["missed"] > 0


def test_the_librarys_refine_starts_from_the_zero_a_fit_would_choose(written):
    """Called directly on the loaded files, ``refine`` starts from the rest position the fit
    and the command line choose (here the identified zero: its mechanistic model meets
    every point), not from each point's own mean, which the user can still ask for by
    choosing that zero first."""
    from ude_fit.discovery.loop import refine
    folder, _ = written
    ds = load(folder, "flutter")
    added = [("heave_unsteady_aero", None)]
    chosen = refine(ds, "flutter", added, bootstrap=10)
    assert chosen.before.metrics.summary.missed == 0
    assert chosen.after.metrics.summary.missed == 0
    own = refine(with_sensor_zero(ds, zero="own-means"), "flutter", added, bootstrap=10)
    assert own.before.metrics.summary.missed > 0


def test_a_configuration_without_a_campaigns_two_orbits_is_refused(tmp_path):
    # the large orbits of this one are unstable as well: no CBC campaign of the lab's
    # layout (a stable and an unstable orbit at each airspeed) comes from it
    with pytest.raises(ValueError, match="not one stable and one unstable orbit"):
        write_lee_campaign(tmp_path, ("k_alpha3=2000", "c_alpha=1.3", "m_T=18"), sigma=0.0,
                           seed=0, record_s=0.1)
    assert not list(tmp_path.glob("*.mat"))


def test_a_point_the_board_did_not_hold_is_refused(tmp_path):
    # the soft configuration's stable orbits (11-13 mm) under the board's largest noise: the
    # response decays to rest while the target still asks for the orbit, which no CBC run
    # would accept as a point
    soft = ("k_alpha=26.03", "I_alpha=0.0829", "k_h=3529.4", "x_alpha=0.24")
    with pytest.raises(ValueError, match="was not held"):
        write_lee_campaign(tmp_path, soft, sigma=0.04, seed=0, n_speeds=3, n_stable=3,
                           record_s=8.0)


def test_a_rest_position_moved_by_a_lift_at_rest_is_found_at_every_airspeed(written, tmp_path):
    """A planted effect: an aerofoil whose load-free incidence is not its rest angle carries
    a static lift growing as V^2, which moves its heave's rest position with the airspeed
    (the heave enters the rig's equations only through its spring and rates, so the orbits
    are the configured rig's, shifted). Planted here as 4 mm per (20 m/s)^2 on each file's
    heave: every orbit comes out about its own airspeed's rest position, and the stiffness
    as without it."""
    import scipy.io

    folder, _ = written
    per_v2 = 0.004 / 20.0 ** 2
    for src in sorted(folder.glob("*.mat")):
        m = scipy.io.loadmat(str(src))
        data = m["data"].copy()
        V = float(np.ravel(m["Wind_sped"])[0])
        data[0] += per_v2 * V ** 2 / HEAVE_M_PER_V
        scipy.io.savemat(str(tmp_path / src.name),
                         {**{k: v for k, v in m.items() if not k.startswith("__")},
                          "data": data})
    plain = with_sensor_zero(load(folder, "flutter"), zero="identified")
    lifted = with_sensor_zero(load(tmp_path, "flutter"), zero="identified")
    assert lifted.sensor_zero.identified and plain.sensor_zero.identified
    # the rest position at each airspeed: the same orbits about it, to a tenth of a mm
    for a, b in zip(plain, lifted):
        assert a.parameter == b.parameter
        assert b.coeffs[0, 0] == pytest.approx(a.coeffs[0, 0], abs=1e-4)
        assert b.coeffs[1, 0] == pytest.approx(a.coeffs[1, 0], abs=1e-4)
    V = lifted.parameters()
    assert lifted.sensor_zero.deflection_span[0] == pytest.approx(
        per_v2 * np.ptp(V ** 2), rel=0.1)
    assert abs(plain.sensor_zero.deflection_span[0]) < 0.1 * per_v2 * np.ptp(V ** 2)
    _, data, *_ = prepare(lifted, "flutter", None, 32)
    p = identify_mechanistic(data, "flutter")[1]["parameters"]
    np.testing.assert_allclose([p["k_alpha"], p["k_alpha2"], p["k_alpha3"]],
                               [70.0, 774.7, 3490.7], rtol=0.03)


def test_an_airspeed_reading_error_moves_the_recorded_airspeed_not_the_orbit(tmp_path):
    # the benchmark's planted scatter: the files say where the tunnel's reading put each
    # point, the records are still the rig's orbits at the airspeed it was held at
    exact = write_lee_campaign(tmp_path / "exact", PHYSICS, sigma=0.0, seed=3, n_speeds=2,
                               n_stable=1, record_s=2.0)
    read = write_lee_campaign(tmp_path / "read", PHYSICS, sigma=0.0, seed=3, n_speeds=2,
                              n_stable=1, record_s=2.0, airspeed_error=0.3)
    assert [p["airspeed"] for p in read["points"]] == [p["airspeed"] for p in exact["points"]]
    assert all(p["recorded"] == p["airspeed"] for p in exact["points"])
    offsets = np.array([p["recorded"] - p["airspeed"] for p in read["points"]])
    assert np.all(offsets != 0.0) and np.all(np.abs(offsets) < 5 * 0.3)
    ds = load(tmp_path / "read", "flutter")
    by_name = {o.source.rsplit("/", 1)[-1]: o for o in ds}
    for p, q in zip(read["points"], exact["points"]):
        assert p["file"] == f"CBC_{'stable' if p['stable'] else 'unstable'}_v" + \
            f"{p['recorded']:.1f}".replace(".", "_") + ".mat"
        assert by_name[p["file"]].parameter == pytest.approx(p["recorded"])
        a = scipy_io_data(tmp_path / "read" / p["file"])
        b = scipy_io_data(tmp_path / "exact" / q["file"])
        assert np.array_equal(a, b)     # the same board run, its own random stream untouched
    # the benchmark's yardstick, the rig's own diagram judged on the files: on the orbits'
    # own airspeeds it meets the points to the record's precision, at the readings it does not
    exact_rms, read_rms = (truth_on_points(str(tmp_path / f), PHYSICS)["branch_rms"]
                           for f in ("exact", "read"))
    assert exact_rms < 1e-3 and read_rms > 10 * exact_rms, (exact_rms, read_rms)
    with pytest.raises(ValueError, match="airspeed_error"):
        write_lee_campaign(tmp_path / "bad", PHYSICS, sigma=0.0, seed=0, airspeed_error=-0.1)


def scipy_io_data(path):
    import scipy.io
    return scipy.io.loadmat(str(path))["data"]


def test_a_target_off_the_orbit_holds_the_point_off_it_with_the_control(tmp_path):
    # the benchmark's planted invasiveness: each point's target off its open-loop orbit by
    # a few per cent; the board's control holds the response off the orbit on the target's
    # side (past it for an unstable orbit, whose own dynamics push away from it), and the
    # control record carries the first harmonic that does so
    truth = write_lee_campaign(tmp_path, PHYSICS, sigma=0.0, seed=1, n_speeds=2, n_stable=1,
                               record_s=2.0, target_error=0.05)
    ds = load(tmp_path, "flutter")
    by_name = {o.source.rsplit("/", 1)[-1]: o for o in ds}
    scales = np.array([p["target_scale"] for p in truth["points"]])
    assert np.all(np.abs(scales - 1.0) > 1e-3)
    for p in truth["points"]:
        o = by_name[p["file"]]
        held = o.amplitude / p["amplitude"]
        offset = p["target_scale"] - 1.0
        assert np.sign(held - 1.0) == np.sign(offset), (p, held)
        assert abs(held - 1.0) > 0.5 * abs(offset), (p, held)
        u = scipy_io_data(tmp_path / p["file"])[2]
        assert np.ptp(u) > 0.0
    with pytest.raises(ValueError, match="target_error"):
        write_lee_campaign(tmp_path / "bad", PHYSICS, sigma=0.0, seed=0, target_error=0.6)
