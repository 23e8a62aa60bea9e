"""The real wind-tunnel measurements (lee2020/model2: 11 CBC points, 4 stable, 7 unstable):
mechanistic and UDE models fitted with the default command, as a user would run it on them
(`ude-fit fit model2 --system flutter`; one start instead of 16, for CI's time).

The default aerofoil network is rest-free (its Hopf point is the mechanistic model's and the
explicit linear terms', not the network's extrapolation to rest), starts from the mechanistic
model (no fit to the residual forces, which bent the branch into S shapes), takes each
labelled orbit's stability margin from the points' Hopf normal-form backbone and its branch's
line, and is held by constraint rounds to the energy-rising and rest-stability conditions,
with no weight set by hand; an orbit labelled stable is held inside the unit circle against
period doubling and torus bifurcations as well as folds; a start whose diagram still folds
more than once gets guide rounds (docs/fitting.md). Measured with five starts on seeds 0-4:
4, 5, 5, 5, 4 of 5 adequate, every kept start under the data's scatter (0.8-3.2 %) with its
Hopf point within 0.33 m/s of the data's estimate (docs/benchmarks.md, 2026-12-04).
"""

from __future__ import annotations

import json

import pytest

from ude_fit import cli
from ude_fit.analysis.metrics import FOLD_TOLERANCE

import jax  # noqa: E402  (after the imports above, before any array)

jax.config.update("jax_enable_x64", True)       # ude_fit computes in float64 (see ude_fit docs)


# the one-start fit takes about 3.5 min beside the other CI worker on 2 cores, 8.5 on a
# machine 2.4 times slower (CI order and time limit: tests/conftest.py)
pytestmark = pytest.mark.minutes(5)


@pytest.fixture(scope="module")
def lee_fit(lee2020_dir, tmp_path_factory):
    out = tmp_path_factory.mktemp("lee_fit")
    rc = cli.main(["fit", str(lee2020_dir / "model2"), "--system", "flutter",
                   "--starts", "1", "--seed", "0", "--out", str(out), "--quiet"])
    with open(out / "metrics.json") as fh:
        return rc, json.load(fh), out


def test_both_models_fitted_to_the_11_points(lee_fit):
    rc, m, out = lee_fit
    assert rc == 0
    assert m["data"]["points"] == 11 and m["data"]["stable"] == 4 and m["data"]["unstable"] == 7
    # the unconstrained least-squares heave damping on the real data is negative: bounded
    # at 0 (never replaced by another rig's values), and said so
    ident = m["mechanistic"]["identification"]
    assert ident["at_bound"] == ["c_h"] and ident["unconstrained"]["c_h"] < 0
    assert m["mechanistic"]["parameters"]["c_h"] == 0.0
    assert "physical bound 0" in ident["sources"]["c_h"]
    assert set(ident["sources"]) >= {"b", "m_T", "c_h", "k_h", "k_alpha3"}
    assert (out / "ude.eqx").exists() and (out / "diagram.png").exists()
    # the files record neither sensor's zero: the default (auto) keeps each point's own
    # mean, the mechanistic model missing every point with the identified zero as well
    zero = m["data"]["sensor_zero"]
    assert not zero["identified"] and zero["points"] == 11
    assert zero["method"].startswith("each point's own mean; chosen (auto)")
    assert zero["judged"]["identified"]["missed"] == 11
    assert m["options"]["sensor_zero"] == "auto"


def test_ude_reproduces_every_point_with_its_stability(lee_fit):
    _, m, _ = lee_fit
    pts = m["ude"]["points"]
    assert len(pts) == 11
    assert m["ude"]["missed"] == 0
    assert all(p["model_stable"] == p["stable"] for p in pts)
    assert m["ude"]["branch_rms"] <= 0.05
    mech = m["mechanistic"]["branch_rms"]      # None: it has no orbit at any point
    assert mech is None or m["ude"]["branch_rms"] < mech
    if mech is None:     # then the points' own backbone sets the adequacy bar
        assert m["starts"]["criterion"]["below_backbone"] is True
        bar = m["backbone"]["branch_rms"]
        assert all(r["metrics"]["branch_rms"] < bar for r in m["starts"]["records"]
                   if r["adequate"])


def _figure(x) -> str:
    # a model that misses every point has no branch RMS (the bounded mechanistic model does)
    return "—" if x is None else f"{x:.4f}"


def test_the_hopf_point_is_where_the_unstable_orbits_point(lee_fit, capsys):
    _, m, _ = lee_fit
    with capsys.disabled():
        print("\nlee2020 model2: mechanistic branch RMS "
              f"{_figure(m['mechanistic']['branch_rms'])} (missed "
              f"{m['mechanistic']['missed']}), UDE {_figure(m['ude']['branch_rms'])}; starts "
              + ", ".join(f"{r['start']}: {_figure(r['metrics']['branch_rms'])}/"
                          f"{r['metrics']['missed']}/{r['metrics']['fold_count']} folds"
                          f"{'*' if r['adequate'] else ''}"
                          for r in m["starts"]["records"] if r.get("metrics")))
    # every start's Hopf point lies beyond the last unstable orbit (25.8 m/s): the
    # equilibrium that orbit surrounds is stable (the rest-stability condition holds there)
    for r in m["starts"]["records"]:
        assert r["metrics"]["hopf"]["model"] > 25.8, r["metrics"]["hopf"]
    # the smaller unstable orbits grow as the airspeed falls (a subcritical Hopf point), and
    # every start's criticality is reported at its own Hopf point
    assert m["data"]["unstable_amplitude2_slope"] < 0
    for r in m["starts"]["records"]:
        assert r["hopf_criticality"]["param"] == pytest.approx(r["metrics"]["hopf"]["model"],
                                                               rel=1e-9)
    # every start's training ends meeting both conditions the constraint rounds hold it to;
    # a guide round's model is checked again, and the record says what the kept model breaks
    # (measured: the second start's one round broke both, by little: its Hopf point is
    # 0.07 m/s beyond the last unstable orbit)
    for r in m["starts"]["records"]:
        g = r.get("guide_rounds")
        if g is None:
            assert r["info"]["constraints_met"] is True, r["info"]
            continue
        assert g["constraints_broken_before"] == [], g
        kept = g["rounds"][g["kept_round"] - 1]["constraints_broken"] if g["kept_round"] else []
        assert r["info"]["constraints_met"] is (kept == []), (r["info"], g)


def test_the_kept_hopf_point_is_where_the_unstable_orbits_point(lee_fit):
    # the data's estimate (26.34 m/s), where the shrinking unstable orbits' amplitude^2
    # line reaches zero: the issue asks within 0.5 m/s
    hopf = lee_fit[1]["ude"]["hopf"]
    assert hopf["model"] is not None and abs(hopf["model"] - hopf["reference"]) <= 0.5


def test_the_kept_diagram_turns_once(lee_fit):
    # the issue: at most one fold; the data has stable and unstable orbits, which meet at
    # one (seeds 0-4 with five starts: 19.6-20.3 m/s). Every point has its orbit, so the
    # fold lies below them all (or within the tolerance at which a point may sit on it)
    ude, points = lee_fit[1]["ude"], lee_fit[1]["data"]["point_records"]
    folds = ude["folds"] + ude["isola_folds"]
    assert len(folds) == 1, folds
    airspeeds = [p["parameter"] for p in points]
    span = max(airspeeds) - min(airspeeds)
    assert folds[0] <= min(airspeeds) + FOLD_TOLERANCE * span


def test_guide_rounds_run_only_where_a_start_breaks_the_diagram_rule(lee_fit):
    _, m, _ = lee_fit
    # the mechanistic model misses every point (no fold of its own): one is allowed
    excess = lambda folds, missed: max(folds - 1, 0) + missed
    for r in m["starts"]["records"]:
        g = r.get("guide_rounds")
        if g is None:                       # the trained start had the data's picture
            assert r["metrics"]["fold_count"] == 1 and r["metrics"]["missed"] == 0, r
            continue
        before = excess(g["folds_before"], g["missed_before"])
        assert g["folds_allowed"] == 1 and before > 0 and g["rounds"]
        assert [x["weight"] for x in g["rounds"]] == pytest.approx(
            [0.3 * 3 ** i for i in range(len(g["rounds"]))])
        if g["kept_round"]:
            kept = g["rounds"][g["kept_round"] - 1]
            assert r["metrics"]["fold_count"] == kept["folds"]
            assert r["metrics"]["missed"] == kept["missed"] <= g["missed_before"]
            assert excess(kept["folds"], kept["missed"]) < before


def test_at_least_80_percent_of_starts_adequate(lee_fit):
    # with the default's five starts 4, 5, 5, 5, 4 of 5 on seeds 0-4 (2026-12-04, b18aa97)
    # (benchmarks/lee2020_benchmark.py; docs/benchmarks.md)
    _, m, _ = lee_fit
    assert m["starts"]["adequate"] >= 0.8 * m["starts"]["requested"], m["starts"]["records"]
    # the kept start is within the data's own scatter
    assert m["ude"]["branch_rms"] <= m["data"]["scatter"]
