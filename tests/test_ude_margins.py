"""Stability margins from the data (ude_fit.analysis.margins) against the rig's own truth: the
Hopf normal-form backbone through the truth's orbits predicts how unstable each unstable
orbit is no more than it is, each branch's straight line keeps the stable orbits' prediction
near the truth's where the backbone's quadratic alone overshoots it, and the periodic
objective holds each orbit at its own margin."""
from __future__ import annotations

import jax
import numpy as np
import pytest

from tests.ude_fixtures import DEFAULT_AIRSPEEDS, flutter_truth_orbits
from ude_fit import UDE, flutter_qs
from ude_fit.analysis.backbone import fit_backbone
from ude_fit.data.load import load
from ude_fit.analysis.criticality import equilibrium_eigenvalues, growth_rate_slope
from ude_fit.analysis.margins import BranchSlope, SLOPE_STEP, backbone_margins, predict_margin

jax.config.update("jax_enable_x64", True)


@pytest.fixture(scope="module")
def truth():
    recs = flutter_truth_orbits(DEFAULT_AIRSPEEDS)
    V = np.array([r["parameter"] for r in recs])
    A = np.array([r["amplitude"] for r in recs])
    return recs, fit_backbone(V, A, [r["stable"] for r in recs])


def _prediction(model, backbone, rec, m, branch=None):
    lam = equilibrium_eigenvalues(model, rec["parameter"])
    return predict_margin(backbone, m, rec["amplitude"], rec["period"], rec["stable"],
                          lam[np.argsort(np.real(lam))[:-2]], branch)


def _line(backbone, recs, stable):
    return BranchSlope.through([(r["amplitude"] / backbone.r_scale) ** 2
                                for r in recs if r["stable"] is stable],
                               [r["parameter"] for r in recs if r["stable"] is stable])


def test_the_unstable_orbits_are_predicted_no_more_unstable_than_the_truth(truth):
    """An unstable orbit's largest Floquet multiplier is its amplitude's: the prediction's
    amplitude factor 1 - exp(lambda T) lies between 0 and the truth's 1 - mu (the rig has
    unsteady aerodynamics the quasi-steady model used for m lacks)."""
    recs, backbone = truth
    model = UDE(flutter_qs())
    m = growth_rate_slope(model, backbone.hopf, SLOPE_STEP)
    assert m > 0                  # the aerofoil's equilibrium loses stability as V rises
    unstable = [r for r in recs if not r["stable"]]
    assert len(unstable) >= 3
    for r in unstable:
        p = _prediction(model, backbone, r, m)
        assert p.exponent_T is not None and p.exponent_T > 0
        factor = 1 - np.exp(p.exponent_T)
        assert 1 - r["floquet_max"] < factor < 0
        assert p.margin == pytest.approx(abs(factor * p.others))


def test_the_branch_line_keeps_the_stable_orbits_near_the_truth():
    """A campaign down to 0.2 m/s above the fold (truth fold 16.82 m/s): the quadratic
    through both branches gives the large stable orbits 5-7 times the truth's slope, so
    alone it predicts amplitude factors 1 - exp(lambda T) of 0.96-1.0 where the truth's
    1 - mu are 0.54-0.57; with the stable branch's own line the prediction stays within
    the m error (the equilibrium's growth-rate slope stands for the orbit's: 0-14 % over)."""
    recs = flutter_truth_orbits((17.0, 18.0, 19.0, 20.0, 21.0, 22.0, 23.0, 23.6))
    backbone = fit_backbone(np.array([r["parameter"] for r in recs]),
                            np.array([r["amplitude"] for r in recs]),
                            [r["stable"] for r in recs])
    model = UDE(flutter_qs())
    m = growth_rate_slope(model, backbone.hopf, SLOPE_STEP)
    line = _line(backbone, recs, True)
    assert line is not None and line.slope > 0
    alone, with_line = [], []
    for r in recs:
        if not r["stable"]:
            continue
        p, q = _prediction(model, backbone, r, m), _prediction(model, backbone, r, m, line)
        if p.exponent_T is None:        # the orbit next to the fold: no prediction either way
            assert q.exponent_T is None
            continue
        truth_factor = 1 - r["floquet_max"]
        alone.append((1 - np.exp(p.exponent_T)) / truth_factor)
        with_line.append((1 - np.exp(q.exponent_T)) / truth_factor)
        assert 0 < with_line[-1] <= alone[-1]
    assert len(with_line) >= 5
    assert max(alone) > 1.5
    assert max(with_line) < 1.2


def test_a_branch_line_needs_three_orbits():
    assert BranchSlope.through([0.1, 0.2], [20.0, 21.0]) is None
    b = BranchSlope.through([0.1, 0.2, 0.3, 0.4], [20.0, 21.0, 22.0, 23.0])
    assert b.slope == pytest.approx(10.0) and b.std == pytest.approx(0.0, abs=1e-9)


def test_a_label_the_backbone_disagrees_with_gets_no_prediction(truth):
    recs, backbone = truth
    model = UDE(flutter_qs())
    m = growth_rate_slope(model, backbone.hopf, SLOPE_STEP)
    r = next(r for r in recs if not r["stable"])
    flipped = {**r, "stable": True}
    assert _prediction(model, backbone, flipped, m).margin is None
    # the opposite growth-rate sign makes every label disagree
    assert _prediction(model, backbone, r, -m).margin is None
    # a branch line of the other sign (or within its error of flat) leaves no prediction
    assert _prediction(model, backbone, r, m).margin is not None
    assert _prediction(model, backbone, r, m, BranchSlope(10.0, 1.0)).margin is None
    assert _prediction(model, backbone, r, m, BranchSlope(-10.0, 11.0)).margin is None


def test_the_dataset_margins_never_fall_below_the_floor(tmp_path, truth):
    """On a campaign file of the truth's orbits: every labelled orbit's margin is predicted
    or nan, and none is below the floor; a floor above every prediction is every margin."""
    from tests.ude_fixtures import write_truth_campaign
    path = tmp_path / "truth.h5"
    write_truth_campaign(path, "flutter")
    ds = load(path, system="flutter")
    model = UDE(flutter_qs())
    margins = backbone_margins(ds, model, floor=0.02)
    v = margins.values
    assert v.shape == (len(ds),)
    assert np.all(np.isnan(v) | (v >= 0.02))
    assert np.sum(np.isfinite(v)) >= len(ds) - 2       # at most the orbits by the fold
    high = backbone_margins(ds, model, floor=5.0).values
    assert np.all(np.isnan(high) | (high == 5.0))
    points = margins.to_json()["points"]
    assert points[0].keys() == {"exponent_T", "others", "margin", "used"}
    assert [p["used"] for p in points] == [None if np.isnan(x) else x for x in v]
    lines = margins.to_json()["branch_slopes"]
    assert lines["stable"]["slope"] > 0 > lines["unstable"]["slope"]
    # each branch's orbit nearest the fold (the lowest airspeed: the fold lies below the
    # Hopf point) has no prediction, whatever the forms say
    low = min(o.parameter for o in ds)
    assert margins.to_json()["next_to_fold"] == {"stable": low, "unstable": low}
    for o, x in zip(ds, v):
        if o.parameter == low:
            assert np.isnan(x)


def test_the_orbit_next_to_the_fold_is_on_the_folds_side():
    from ude_fit.analysis.backbone import HopfBackbone
    from ude_fit.analysis.margins import _next_to_fold
    cov = np.zeros((3, 3))
    below = HopfBackbone(25.0, -30.0, 40.0, 0.1, 1, cov, 0.0)      # fold at 19.4 m/s
    above = HopfBackbone(25.0, 30.0, -40.0, 0.1, -1, cov, 0.0)     # fold at 30.6 m/s
    none = HopfBackbone(25.0, -30.0, -40.0, 0.1, 1, cov, 0.0)      # monotone: no fold
    assert below.fold < 25.0 < above.fold and none.fold is None
    assert _next_to_fold(below, [21.0, 20.0, 23.0]) == 20.0
    assert _next_to_fold(above, [21.0, 20.0, 23.0]) == 23.0
    assert _next_to_fold(none, [21.0, 20.0]) is None
    assert _next_to_fold(below, []) is None


def test_a_stage_keeps_the_margins_of_its_orbits(tmp_path):
    import dataclasses

    import jax.numpy as jnp

    from tests.ude_fixtures import write_truth_campaign
    from ude_fit.training.identify import training_data
    path = tmp_path / "truth.h5"
    write_truth_campaign(path, "flutter")
    data = training_data(load(path, system="flutter"))
    margins = np.linspace(0.02, 0.5, data.n_orbits)
    data = dataclasses.replace(data, margin=jnp.asarray(margins))
    mask = np.arange(data.n_orbits) % 2 == 1
    idx = np.where(mask, np.arange(data.n_orbits), np.flatnonzero(mask)[0])
    np.testing.assert_array_equal(np.asarray(data.only(mask).margin), margins[idx])
    np.testing.assert_array_equal(np.asarray(data.measurements().margin), margins)


def test_the_report_lists_each_labelled_points_margin(tmp_path):
    from tests.ude_fixtures import write_truth_campaign
    from ude_fit.report.markdown import _margins
    path = tmp_path / "truth.h5"
    write_truth_campaign(path, "flutter")
    ds = load(path, system="flutter")
    margins = backbone_margins(ds, UDE(flutter_qs()), floor=0.02)
    text = " ".join(_margins(margins.to_json(), ds.point_records(), "m/s"))
    shown = [p for p in margins.points if p.margin is not None]
    assert text.count("(constant)") == len(ds) - len(shown)
    for o, p in zip(ds, margins.points):
        if p.margin is not None:
            assert (f"{o.parameter:.2f} m/s {'stable' if o.stable else 'unstable'} "
                    f"{max(p.margin, 0.02):.3f}") in text
    assert _margins(None, [], "m/s") == []
