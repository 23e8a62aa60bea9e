"""ude_fit's dataset of periodic orbits, judged against the rigs' true orbits and the real
lee2020 wind-tunnel files.

Truth: campaign files whose points are rig_sim's own periodic orbits (tests/ude_fixtures.py),
noise-free, or with raw records taken from the rig's board held on them.
"""

from __future__ import annotations

import math
import time

import h5py
import numpy as np
import pytest
import scipy.io

from tests import ude_fixtures as F
from ude_fit._fourier import evaluate, fourier_fit, K, refine_frequency, shift_phase
from ude_fit.data.campaign import load_campaign
from ude_fit.data.lee import load_lee
from ude_fit.data.load import load
from ude_fit.data.orbit import DataError, Orbit, OrbitDataset

import jax  # noqa: E402  (after the imports above, before any array)

jax.config.update("jax_enable_x64", True)       # ude_fit computes in float64 (see ude_fit docs)

LEE_STABLE_V = [20.7, 21.5, 22.4, 23.2]                      # README table, m/s
LEE_UNSTABLE_V = [20.7, 21.6, 22.4, 23.3, 24.1, 25.0, 25.8]


def fundamental(c) -> complex:
    """a1 - i b1: q ~ Re(z e^{i phi})."""
    return complex(c[1], -c[1 + K])


# ---- shared files (module scope: the truth continuation takes seconds) ----------------------

@pytest.fixture(scope="module")
def flutter_truth(tmp_path_factory):
    path = tmp_path_factory.mktemp("ude") / "flutter_truth.h5"
    return path, F.write_truth_campaign(path, "flutter")


@pytest.fixture(scope="module")
def oscillator_truth(tmp_path_factory):
    path = tmp_path_factory.mktemp("ude") / "oscillator_truth.h5"
    return path, F.write_truth_campaign(path, "oscillator", freqs=(21.0, 23.0), per_freq=4)


NOISY = dict(airspeeds=(20.7, 23.0), sigma=0.02, seed=5, record_s=4.0)


@pytest.fixture(scope="module")
def flutter_noisy(tmp_path_factory):
    path = tmp_path_factory.mktemp("ude") / "flutter_noisy.h5"
    return path, F.write_truth_campaign(path, "flutter", **NOISY)


@pytest.fixture(scope="module")
def oscillator_records(tmp_path_factory):
    d = tmp_path_factory.mktemp("ude")
    kw = dict(freqs=(23.0,), per_freq=3, seed=2, record_s=1.0)
    truth = F.write_truth_campaign(d / "rec.h5", "oscillator", **kw)
    F.write_truth_campaign(d / "means.h5", "oscillator", keep_record=False, **kw)
    return d / "rec.h5", d / "means.h5", truth


@pytest.fixture(scope="module")
def lee(lee2020_dir):
    t0 = time.perf_counter()
    ds = load_lee(lee2020_dir / "model2")
    return ds, time.perf_counter() - t0


# ---- truth campaigns -------------------------------------------------------------------------

def test_flutter_truth_campaign_loads_every_orbit_exactly(flutter_truth):
    path, truth = flutter_truth
    ds = load([str(path)])
    assert ds.system == "flutter" and ds.sources == (str(path),)
    assert len(ds) == len(truth) == 10                 # 4 bistable airspeeds x 2 + 2 above Hopf
    assert ds.coordinates == ("h", "alpha")
    np.testing.assert_array_equal(ds.parameters(), [t["parameter"] for t in truth])
    np.testing.assert_array_equal(ds.stable(), [t["stable"] for t in truth])
    assert ds.stable().sum() == 6
    np.testing.assert_allclose(ds.amplitudes(), [t["amplitude"] for t in truth], rtol=1e-6)
    np.testing.assert_allclose(ds.frequencies(), [t["frequency"] for t in truth], rtol=1e-12)
    for o, t in zip(ds, truth):
        assert o.forcing is None and np.all(np.isnan(o.noise)) and o.source.startswith(str(path))
        # canonical frame: heave fundamental +A cos(phi) ...
        assert o.coeffs[0, 1] > 0 and abs(o.coeffs[0, 1 + K]) < 1e-12 * o.amplitude
        # ... reached by a pure time shift: every harmonic's size kept, and the pitch keeps
        # its phase relative to the heave
        for k in range(1, K + 1):
            np.testing.assert_allclose(np.hypot(o.coeffs[:, k], o.coeffs[:, K + k]),
                                       np.hypot(t["coeffs"][:, k], t["coeffs"][:, K + k]),
                                       rtol=1e-9, atol=1e-15)
        ratio = fundamental(o.coeffs[1]) / fundamental(o.coeffs[0])
        ratio_t = fundamental(t["coeffs"][1]) / fundamental(t["coeffs"][0])
        assert abs(ratio - ratio_t) < 1e-9 * abs(ratio_t)
        assert math.hypot(o.coeffs[1, 1], o.coeffs[1, 1 + K]) == pytest.approx(t["pitch_amp"],
                                                                               rel=1e-6)


def test_oscillator_truth_campaign_keeps_the_forcing_frame(oscillator_truth):
    path, truth = oscillator_truth
    ds = load_campaign(path)
    assert ds.system == "oscillator" and ds.coordinates == ("x",)
    # per frequency: one orbit below the folds, three at each of 2 forcings between, one above
    assert len(ds) == len(truth) == 2 * 8
    np.testing.assert_array_equal(ds.frequencies_group(), [21.0, 23.0])
    for f in (21.0, 23.0):
        sub = ds.at_frequency(f)
        assert len(sub) == 8 and sub.stable().sum() == 6
    np.testing.assert_array_equal(ds.stable(), [t["stable"] for t in truth])
    np.testing.assert_allclose(ds.parameters(), [t["parameter"] for t in truth], rtol=1e-12)
    np.testing.assert_allclose(ds.amplitudes(), [t["amplitude"] for t in truth], rtol=1e-6)
    for o, t in zip(ds, truth):
        # the truth's frame is already "forcing = Phi cos(phi)": nothing may move
        np.testing.assert_allclose(o.coeffs, t["coeffs"], rtol=0, atol=1e-12 * o.amplitude)
        np.testing.assert_allclose(o.forcing, t["forcing"], atol=1e-12 * o.parameter)
    # the unstable middle orbits lie between the stable ones at the same forcing
    for f in (21.0, 23.0):
        sub = ds.at_frequency(f)
        for P in np.unique(sub.parameters()):
            at = sub.select(sub.parameters() == P)
            if len(at) == 3:
                order = np.argsort(at.amplitudes())
                assert list(at.stable()[order]) == [True, False, True]


def test_sample_gives_the_series_and_its_exact_time_derivatives(flutter_truth, oscillator_truth):
    ds = load(str(flutter_truth[0]))
    n = 2048
    s = ds.sample(n)
    assert s["phase"].shape == (n,) and s["q"].shape == (len(ds), n, 2)
    assert "forcing" not in s
    np.testing.assert_allclose(s["q"][:, 0, :], ds.coeffs()[:, :, 0]
                               + ds.coeffs()[:, :, 1:K + 1].sum(-1), atol=1e-15)
    dt = 1.0 / (ds.frequencies()[:, None, None] * n)
    fd1 = (np.roll(s["q"], -1, axis=1) - np.roll(s["q"], 1, axis=1)) / (2 * dt)
    fd2 = (np.roll(s["q"], -1, axis=1) - 2 * s["q"] + np.roll(s["q"], 1, axis=1)) / dt ** 2
    scale1 = np.abs(s["qdot"]).max(axis=1, keepdims=True)
    scale2 = np.abs(s["qddot"]).max(axis=1, keepdims=True)
    assert np.all(np.abs(fd1 - s["qdot"]) < 1e-4 * scale1)        # O((w dt)^2) differences
    assert np.all(np.abs(fd2 - s["qddot"]) < 1e-4 * scale2)
    # analytic: q = cos(phi) + 0.5 sin(3 phi) at 2 Hz
    c = np.zeros((1, 2 * K + 1))
    c[0, 1], c[0, K + 3] = 1.0, 0.5
    one = OrbitDataset("flutter", (Orbit(10.0, 2.0, None, np.vstack([c, c]), None, np.nan, 1.0,
                                         "synthetic"),), ("synthetic",))
    s1 = one.sample(64)
    w, ph = 4 * np.pi, s1["phase"]
    np.testing.assert_allclose(s1["q"][0, :, 0], np.cos(ph) + 0.5 * np.sin(3 * ph), atol=1e-14)
    np.testing.assert_allclose(s1["qdot"][0, :, 0], w * (-np.sin(ph) + 1.5 * np.cos(3 * ph)),
                               atol=1e-12)
    np.testing.assert_allclose(s1["qddot"][0, :, 0], -w ** 2 * (np.cos(ph) + 4.5 * np.sin(3 * ph)),
                               atol=1e-10)
    # oscillator: the forcing is sampled in the same frame (here Phi cos(phi))
    dso = load(str(oscillator_truth[0]))
    so = dso.sample(32)
    assert so["forcing"].shape == (len(dso), 32)
    np.testing.assert_allclose(so["forcing"], dso.parameters()[:, None] * np.cos(so["phase"]),
                               atol=1e-12)


def test_dataset_helpers(flutter_truth):
    ds = load(str(flutter_truth[0]))
    st = ds.select(ds.stable())
    assert len(st) == 6 and st.stable().all() and st.sources == ds.sources
    assert len(ds.select([0, 2])) == 2 and ds.select([0, 2])[1] is ds[2]
    assert ds.noise().shape == (10, 2) and ds.coeffs().shape == (10, 2, 15)
    assert ds.forcings() is None
    with pytest.raises(DataError):
        ds.frequencies_group()                  # flutter frequencies are not groups
    unknown = OrbitDataset("flutter", (Orbit(1.0, 2.0, None, np.zeros((2, 15)), None, np.nan,
                                             1.0, "x"),), ("x",))
    assert not unknown.known_stability().any()
    with pytest.raises(DataError, match="stability unknown"):
        unknown.stable()
    with pytest.raises(ValueError):
        ds[0].coeffs[0, 0] = 1.0                 # orbits are immutable


# ---- Fourier averaging --------------------------------------------------------------------------

def test_fourier_fit_recovers_coefficients_and_frequency_from_a_noisy_record():
    rng = np.random.default_rng(11)
    f_true = 2.4137
    c_true = np.zeros(2 * K + 1)
    c_true[[0, 1, 2, 3, 5, K + 1, K + 2, K + 3, K + 7]] = [0.003, 0.05, 0.004, -0.0015, 7e-4,
                                                          0.02, -0.001, -0.002, 3e-4]
    t = np.arange(0.0, 20.0, 1e-3) + 3.7                 # 48 periods, arbitrary clock offset
    sigma = 0.002                                        # ~4 % of the amplitude, as measured
    y = evaluate(c_true, 2 * np.pi * f_true * (t - t[0])) + sigma * rng.standard_normal(t.size)
    f0 = f_true * 1.005                                  # logged 0.5 % wrong
    f = refine_frequency(t, y, f0)
    assert abs(f / f_true - 1) < 2e-5
    c, rms = fourier_fit(t, y, f)
    assert rms == pytest.approx(sigma, rel=0.05)
    # a frequency error of 1e-5 turns the phase at t[0] by ~1e-3 rad (the fit's phase is the
    # record's average): compare shapes, each with its fundamental put on the cosine
    def aligned(cc):
        return shift_phase(cc, math.atan2(cc[1 + K], cc[1]))
    assert np.max(np.abs(aligned(c) - aligned(c_true))) < 5 * sigma * np.sqrt(2 / t.size)
    assert np.max(np.abs(c - c_true)) < 5e-4 * math.hypot(c_true[1], c_true[1 + K]) * 10
    # why refine: at the logged frequency the phase slips 1.5 rad over the record and the
    # average smears the fundamental
    c_bad, rms_bad = fourier_fit(t, y, f0)
    amp = math.hypot(c_true[1], c_true[1 + K])
    assert abs(math.hypot(c_bad[1], c_bad[1 + K]) - amp) > 0.05 * amp
    assert rms_bad > 3 * sigma
    # several channels at once, same answer
    C, R = fourier_fit(t, np.column_stack([y, 2 * y]), f)
    np.testing.assert_allclose(C[1], 2 * c, rtol=1e-10, atol=1e-14)
    # a short record (5 periods, like two lee2020 files) still finds its frequency
    ts = t[:2000]
    assert abs(refine_frequency(ts, y[:2000], f_true * 0.995) / f_true - 1) < 5e-4


def test_shift_phase_is_a_time_shift():
    rng = np.random.default_rng(3)
    c = rng.normal(size=2 * K + 1)
    phi = np.linspace(0, 2 * np.pi, 50)
    np.testing.assert_allclose(evaluate(shift_phase(c, 0.7), phi), evaluate(c, phi + 0.7),
                               atol=1e-12)


def test_noisy_flutter_records_load_with_noise_and_true_amplitudes(flutter_noisy, tmp_path):
    path, truth = flutter_noisy
    ds = load([str(path)], system="flutter")
    assert len(ds) == 4 and list(ds.stable()) == [t["stable"] for t in truth]
    for o, t in zip(ds, truth):
        assert np.all(o.noise > 0) and np.all(np.isfinite(o.noise))
        assert o.noise[0] < 0.05 * o.amplitude
        assert o.amplitude == pytest.approx(t["amplitude"], rel=0.04), o.source
        assert o.frequency == pytest.approx(t["frequency"], rel=0.005)
        assert o.periods == pytest.approx(4.0 * o.frequency, rel=0.01)
        pitch = math.hypot(o.coeffs[1, 1], o.coeffs[1, 1 + K])
        assert pitch == pytest.approx(t["pitch_amp"], rel=0.08)   # held, not free: a few %
        # same frame as the truth's: the pitch's phase relative to the heave
        ratio = fundamental(o.coeffs[1]) / fundamental(o.coeffs[0])
        ratio_t = fundamental(t["coeffs"][1]) / fundamental(t["coeffs"][0])
        assert abs(np.angle(ratio / ratio_t)) < 0.05
    # the fixture is seeded: the same call writes the same records
    again = tmp_path / "again.h5"
    F.write_truth_campaign(again, "flutter", **NOISY)
    with h5py.File(path, "r") as f1, h5py.File(again, "r") as f2:
        for name in f1["points"]:
            for fld in ("x", "q2", "sample"):
                np.testing.assert_array_equal(f1["points"][name]["timeseries"][fld][()],
                                              f2["points"][name]["timeseries"][fld][()])


def test_oscillator_records_are_fitted_in_the_forcing_frame(oscillator_records):
    rec_path, means_path, truth = oscillator_records
    rec, means = load(str(rec_path)), load(str(means_path))
    assert len(rec) == len(means) == len(truth) == 5
    for o, m, t in zip(rec, means, truth):
        assert 0 < o.noise[0] < 1e-5 and np.isnan(m.noise[0])    # ~2 um sensor noise
        assert o.periods == pytest.approx(23.0, abs=0.1)
        # forcing frame: excitation fundamental is +Phi cos(phi)
        assert o.forcing[1] > 0 and abs(o.forcing[1 + K]) < 1e-12 * o.forcing[1]
        assert math.hypot(o.forcing[1], o.forcing[1 + K]) == pytest.approx(t["parameter"],
                                                                           rel=0.01)
        # the response's phase against the forcing is the truth's (amplitude and phase)
        z, zt = fundamental(o.coeffs[0]), fundamental(t["coeffs"][0])
        assert abs(z - zt) < 0.02 * abs(zt), o.source
        # the board's averaged means (no record) give the same orbit in the same frame
        assert abs(fundamental(m.coeffs[0]) - z) < 0.01 * abs(z)
        assert abs(fundamental(m.forcing) - fundamental(o.forcing)) < 0.01 * o.forcing[1]


# ---- lee2020 ------------------------------------------------------------------------------------

def test_lee2020_model2_loads_as_eleven_orbits(lee, lee2020_dir):
    ds, seconds = lee
    print(f"\nlee2020 model2 loaded in {seconds:.2f} s")
    print(" file                  V m/s  stable  f Hz    heave mm  noise %  pitch mrad  pitch noise %")
    for o in ds:
        pitch = math.hypot(o.coeffs[1, 1], o.coeffs[1, 1 + K])
        print(f" {o.source.split('/')[-1]:21s} {o.parameter:5.1f}  {str(o.stable):6s}  "
              f"{o.frequency:.4f}  {1e3 * o.amplitude:7.2f}  {100 * o.noise[0] / o.amplitude:6.2f}"
              f"  {1e3 * pitch:9.1f}  {100 * o.noise[1] / pitch:6.2f}")
    # (~1 s on an idle 2-core machine; speed is a benchmark's business, not a test's)
    assert len(ds) == 11 and ds.system == "flutter"
    stable = ds.stable()
    assert stable.sum() == 4 and (~stable).sum() == 7
    np.testing.assert_allclose(np.sort(ds.parameters()[stable]), LEE_STABLE_V, atol=1e-9)
    # CBC_v20_7.mat records Wind_sped = 20.6 (its name and the README say 20.7)
    np.testing.assert_allclose(np.sort(ds.parameters()[~stable]), LEE_UNSTABLE_V, atol=0.11)
    for o in ds:
        m = scipy.io.loadmat(o.source, variable_names=["Wind_sped", "freq_actual"])
        assert o.parameter == float(m["Wind_sped"].item())
        assert 2.3 < o.frequency < 2.5
        assert o.frequency == pytest.approx(float(m["freq_actual"].item()), rel=0.01)
        assert o.coeffs[0, 1] > 0 and abs(o.coeffs[0, 1 + K]) < 1e-9 * o.amplitude
        assert abs(o.coeffs[0, 0]) < 0.05 * o.amplitude              # DC offset removed
        # ... and kept in the sensor's frame (its ~3.3 V at 0.18 m/V), which no file records
        assert not o.zero_known and 0.55 < o.sensor_means[0] < 0.65
        assert o.periods > 4.5
    A = ds.amplitudes()
    # stable cycles 45-95 mm growing with speed; unstable ones 5-35 mm, below the stable
    As = A[stable][np.argsort(ds.parameters()[stable])]
    assert np.all((As > 0.045) & (As < 0.095)) and np.all(np.diff(As) > 0)
    assert np.all((A[~stable] > 0.005) & (A[~stable] < 0.035))
    assert A[~stable].max() < As.min()


def test_lee2020_noise_is_a_few_percent(lee):
    ds, _ = lee
    heave = ds.noise()[:, 0] / ds.amplitudes()
    assert np.all((heave > 0.003) & (heave < 0.08))
    assert 0.02 <= np.median(heave) <= 0.05                  # the README's 2-5 %
    # the pitch encoder's dropout bursts are left out: the residual stays a few per cent of
    # the pitch amplitude (a plain unwrap makes it ~100 %)
    pitch = np.hypot(ds.coeffs()[:, 1, 1], ds.coeffs()[:, 1, 1 + K])
    assert np.all(ds.noise()[:, 1] < 0.15 * pitch)
    assert np.all((pitch > 0.003) & (pitch < 0.12))


def test_load_dispatches_by_content_and_concatenates(lee2020_dir, flutter_truth, tmp_path):
    one = lee2020_dir / "model2" / "CBC_stable_v22_4.mat"
    renamed = tmp_path / "stable_point.dat"              # content decides, not the name
    renamed.write_bytes(one.read_bytes())
    ds = load([str(flutter_truth[0]), str(one), str(renamed)], system="flutter")
    assert len(ds) == 12 and len(ds.sources) == 3
    assert ds[10].amplitude == pytest.approx(ds[11].amplitude, rel=1e-12)
    assert ds[10].stable is True and ds[11].stable is None   # name does not say


# ---- errors ------------------------------------------------------------------------------------

def _one_line_error(paths, system=None) -> str:
    with pytest.raises(DataError) as e:
        load(paths, system)
    msg = str(e.value)
    assert "\n" not in msg and msg
    return msg


def test_bad_inputs_are_one_line_data_errors(tmp_path, flutter_truth, oscillator_truth):
    junk = tmp_path / "junk.h5"
    junk.write_bytes(np.random.default_rng(0).bytes(4096))
    assert str(junk) in _one_line_error([str(junk)])

    plain = tmp_path / "plain.h5"
    with h5py.File(plain, "w") as f:
        f["x"] = np.arange(3)
    assert "not a campaign file" in _one_line_error([str(plain)])

    newer = tmp_path / "newer.h5"
    newer.write_bytes(flutter_truth[0].read_bytes())
    with h5py.File(newer, "r+") as f:
        f.attrs["format_version"] = 2
    assert "version 2" in _one_line_error([str(newer)])

    assert "no such file" in _one_line_error([str(tmp_path / "missing.h5")])

    other_mat = tmp_path / "other.mat"
    scipy.io.savemat(other_mat, {"x": np.arange(5.0)})
    assert "not a lee2020" in _one_line_error([str(other_mat)])
    empty_dir = tmp_path / "empty"
    empty_dir.mkdir()
    msg = _one_line_error([str(empty_dir)])                # names both kinds it looked for
    assert "campaign files (.h5, .hdf5)" in msg and ".mat files" in msg

    assert "load one system" in _one_line_error([str(flutter_truth[0]), str(oscillator_truth[0])])
    assert "oscillator was asked for" in _one_line_error([str(flutter_truth[0])], "oscillator")

    hot = tmp_path / "hot.h5"
    hot.write_bytes(flutter_truth[0].read_bytes())
    (tmp_path / "hot.h5-journal").write_bytes(b"x")
    assert "journal" in _one_line_error([str(hot)])


def test_a_campaign_without_complete_ok_points_is_refused(tmp_path, oscillator_truth):
    path = tmp_path / "none_ok.h5"
    path.write_bytes(oscillator_truth[0].read_bytes())
    with h5py.File(path, "r+") as f:
        names = sorted(f["points"])
        for name in names[:-1]:
            f["points"][name].attrs["status"] = "not_converged"
        f["points"][names[-1]].attrs["complete"] = False     # cut short by a kill
    assert len(load_campaign(path)) == 0                     # a campaign just started is fine
    assert "no complete points" in _one_line_error([str(path)])


def test_one_fourier_convention_harmonics_inverts_evaluate():
    """Coefficients are the last axis everywhere: harmonics of the samples of a series
    give back its coefficients, and amplitude reads the first harmonic from them."""
    from ude_fit._fourier import amplitude, harmonics
    c = np.random.default_rng(0).normal(size=(3, 2 * K + 1))
    phi = 2 * np.pi * np.arange(32) / 32
    samples = evaluate(c, phi).T                         # (32 phases, 3 coordinates)
    np.testing.assert_allclose(harmonics(samples), c, atol=1e-12)
    np.testing.assert_allclose(amplitude(c), np.hypot(c[:, 1], c[:, K + 1]))


def test_a_record_whose_sample_counter_jumps_is_fitted_on_its_longest_contiguous_part(
        flutter_noisy, tmp_path):
    """A raw record whose sample counter jumps (ring records overwritten while they were
    read; seen in a campaign resumed on a busy machine) does not date the samples around
    the jump. The loader fits the longest stretch over which the counter steps by one
    sample. Fitting the whole record by its counter put one such point's amplitude 22 %
    below its own board means."""
    import shutil

    path, truth = flutter_noisy
    torn = tmp_path / "jumped.h5"
    shutil.copy(path, torn)
    with h5py.File(torn, "r+") as f:
        name = sorted(f["points"])[0]
        sample = f["points"][name]["timeseries"]["sample"]
        counter = sample[()]
        cut = counter.size // 3                # the longest contiguous part: the last two thirds
        counter[cut:] -= counter[-1] - counter[0] + 5000
        sample[...] = counter
    clean = load([str(path)], system="flutter")[0]
    loaded = load([str(torn)], system="flutter")[0]
    assert loaded.amplitude == pytest.approx(truth[0]["amplitude"], rel=0.04)
    assert loaded.amplitude == pytest.approx(clean.amplitude, rel=0.01)
    assert loaded.periods == pytest.approx(clean.periods * (1 - 1 / 3), rel=0.01)
    assert np.all(np.isfinite(loaded.noise))


def test_a_decimated_record_is_fitted_whole(flutter_noisy, tmp_path):
    """At high time scales the ring keeps one sample in `ring_decimation`; such a record's
    counter steps by that number throughout, and the loader fits all of it, as it fits a
    record kept at every sample."""
    import shutil

    path, truth = flutter_noisy
    thinned = tmp_path / "decimated.h5"
    shutil.copy(path, thinned)
    with h5py.File(thinned, "r+") as f:
        series = f["points"][sorted(f["points"])[0]]["timeseries"]
        for field in list(series):
            kept = series[field][()][::4]
            del series[field]
            series[field] = kept
    clean = load([str(path)], system="flutter")[0]
    loaded = load([str(thinned)], system="flutter")[0]
    assert loaded.amplitude == pytest.approx(truth[0]["amplitude"], rel=0.04)
    assert loaded.amplitude == pytest.approx(clean.amplitude, rel=0.01)
    assert loaded.periods == pytest.approx(clean.periods, rel=0.01)
    assert np.all(np.isfinite(loaded.noise))     # a fitted record, not the board's means

