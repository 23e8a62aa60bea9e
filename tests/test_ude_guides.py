"""Guide orbits (``--guide-orbits``, data.one_fold, training.guides): a curve with one
Hopf point and one fold fitted to the points, its orbits as extra targets of the periodic
loss where the data is silent; checked against a curve of known parameters. (A second fold
planted above the data, which the measured orbits cannot see and the guides can, is the
guide rounds' test: tests/test_ude_guide_rounds.py.)"""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tests.ude_fixtures import write_truth_campaign
from ude_fit import UDE, identify, load, training_data
from ude_fit.data.one_fold import OneFoldCurve, fit_one_fold
from ude_fit.cli import main
from ude_fit.data.orbit import OrbitDataset
from ude_fit.training.guides import GUIDE_TOP, guide_orbits, with_guides
from ude_fit.training.losses import periodic_objective
from ude_fit.training.options import FitOptions, TrainConfig

jax.config.update("jax_enable_x64", True)

# the curve fits and one periodic objective on 4 orbits and their guides
pytestmark = pytest.mark.minutes(1)


@pytest.fixture(scope="module")
def campaign(tmp_path_factory):
    path = tmp_path_factory.mktemp("guides") / "f.h5"
    write_truth_campaign(path, "flutter", airspeeds=(21.0, 23.6))
    ds = load([path], "flutter")
    data = training_data(ds)
    mech, _ = identify(data, "flutter")
    return ds, data, mech


def _points(curve: OneFoldCurve, s, unstable):
    return curve.airspeed(s), np.asarray(s) * curve.amp_scale, np.asarray(unstable)


def _dataset_at(template: OrbitDataset, V, A, unstable) -> OrbitDataset:
    base = template.orbits[0]
    out = [dataclasses.replace(base, parameter=float(v),
                               coeffs=base.coeffs * (a / base.amplitude), stable=not u,
                               source=f"p{i}")
           for i, (v, a, u) in enumerate(zip(V, A, unstable))]
    return OrbitDataset("flutter", tuple(out), tuple(o.source for o in out))


def test_the_curve_has_one_hopf_point_and_one_fold_and_is_recovered(campaign):
    ds, *_ = campaign
    truth = OneFoldCurve(hopf=24.0, fold_s=0.45, log_c=np.log(40.0), tilt=-1.0,
                         amp_scale=0.09, top=1.4, amplitude_rms=0.0)
    u = np.linspace(0.0, 1.4, 400)
    dv = np.diff(truth.airspeed(u))
    assert (dv[u[1:] < 0.44] < 0).all() and (dv[u[:-1] > 0.46] > 0).all()
    s = np.array([0.12, 0.22, 0.3, 0.38, 0.55, 0.7, 0.85, 1.0])
    pts = _dataset_at(ds, *_points(truth, s, s < truth.fold_s))
    fitted = fit_one_fold(pts, 1.4)
    assert fitted.hopf == pytest.approx(truth.hopf, abs=0.05)
    assert fitted.fold == pytest.approx(truth.fold, abs=0.05)
    assert fitted.fold_s == pytest.approx(truth.fold_s, abs=0.02)
    assert fitted.amplitude_rms < 2e-3
    assert fitted.amp_scale == pytest.approx(0.09)


def test_no_curve_without_both_stabilities(campaign):
    ds, *_ = campaign
    stable = OrbitDataset("flutter", tuple(o for o in ds if o.stable), ("s",))
    assert fit_one_fold(stable, 1.4) is None


def test_the_guides_lie_on_the_curve_with_its_stability(campaign):
    ds, *_ = campaign
    curve = fit_one_fold(ds, ds.kind.amplitude_window)
    guides = guide_orbits(ds, curve, 9)
    amps = np.array([o.amplitude for o in guides]) / curve.amp_scale
    smallest = min(o.amplitude for o in ds) / curve.amp_scale
    np.testing.assert_allclose(amps, np.linspace(smallest, GUIDE_TOP, 9), rtol=1e-12)
    np.testing.assert_allclose([o.parameter for o in guides], curve.airspeed(amps))
    step = amps[1] - amps[0]
    for a, o in zip(amps, guides):
        if abs(a - curve.fold_s) < 0.5 * step:
            assert o.stable is None                   # next to the fold: not said
        else:
            assert o.stable == (a > curve.fold_s)
            assert o.stability_from == "one-fold curve"
        assert o.control is None and o.holding is None


def test_guides_weigh_their_heave_alone_and_stay_out_of_the_measurements(campaign):
    ds, data, mech = campaign
    curve = fit_one_fold(ds, ds.kind.amplitude_window)
    guided = with_guides(data, guide_orbits(ds, curve, 5), mech, 0.3)
    assert guided.n_orbits == data.n_orbits + 5 and guided.measured == data.n_orbits
    m = guided.measurements()
    for a, b in ((m.ys, data.ys), (m.qdd, data.qdd), (m.period, data.period),
                 (m.label, data.label), (m.drive.param, data.drive.param)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    np.testing.assert_array_equal(np.asarray(guided.y_scale), np.asarray(data.y_scale))
    cfg = TrainConfig().for_system("flutter")
    params = {"dy0": jnp.zeros(guided.ys[:, 0, :].shape),
              "dT": jnp.zeros(guided.period.shape)}
    value = float(periodic_objective(UDE(mech), params, guided, cfg))
    # a guide's pitch is a stand-in: changing it changes nothing (but where the orbit
    # starts, its first sample)
    ys = np.asarray(guided.ys).copy()
    ys[data.n_orbits:, 1:, 1] *= 3.0
    ys[data.n_orbits:, 1:, 3] += 0.1
    other = eqx.tree_at(lambda d: d.ys, guided, jnp.asarray(ys))
    assert float(periodic_objective(UDE(mech), params, other, cfg)) == value
    # its heave is not
    ys[data.n_orbits:, 1:, 0] *= 1.1
    other = eqx.tree_at(lambda d: d.ys, guided, jnp.asarray(ys))
    assert float(periodic_objective(UDE(mech), params, other, cfg)) > value


@pytest.mark.parametrize("fields, message", [
    (dict(system="oscillator", guide_orbits=8), "applies to --system flutter only"),
    (dict(system="flutter", guide_orbits=8, training="trajectory"), "--training periodic"),
    (dict(system="flutter", guide_orbits=8, approximator="gp"), "--approximator nn"),
    (dict(system="flutter", guide_orbits=8, train=TrainConfig(monotone_rounds=2)),
     "do not combine"),
    (dict(system="flutter", guide_orbits=1), "at least 2"),
    (dict(system="flutter", guide_orbits=8, guide_weight=0.0), "above 0"),
    (dict(system="flutter", guide_orbits=8, guide_weight=float("nan")), "above 0"),
])
def test_guides_are_refused_where_they_do_not_apply(fields, message):
    with pytest.raises(ValueError, match=message):
        FitOptions(**fields)


@pytest.mark.parametrize("argv, message", [
    (["--guide-orbits", "1"], "--guide-orbits must be 0 (none) or an integer at least 2"),
    (["--guide-orbits", "8", "--approximator", "gp"], "--guide-orbits applies to "
     "--approximator nn --training periodic only"),
])
def test_the_command_line_names_a_bad_guide_option(tmp_path, capsys, argv, message):
    out = tmp_path / "out"
    rc = main(["fit", "data.h5", "--system", "flutter", *argv, "--out", str(out), "--quiet"])
    err = capsys.readouterr().err
    assert rc == 2 and message in err and len(err.strip().splitlines()) == 1, err
    assert not out.exists()


def test_the_report_says_what_the_guides_were(campaign):
    from ude_fit.fitting import _guided
    from ude_fit.report.markdown import _guides
    ds, data, mech = campaign
    opts = FitOptions("flutter", guide_orbits=6, guide_weight=0.25)
    guided, record = _guided(ds, data, mech, opts)
    assert guided.n_orbits == data.n_orbits + 6 and len(record["orbits"]) == 6
    assert record["weight"] == 0.25 and record["curve"]["fold"] < record["curve"]["hopf"]
    text = " ".join(_guides(record, "m/s"))
    assert "6 orbits" in text and "weight 0.25" in text
    assert f"fold {record['curve']['fold']:.3f} m/s" in text
    assert _guides(None, "m/s") == []
