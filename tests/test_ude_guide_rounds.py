"""Guide rounds (``--guide-rounds``, ude_fit.guide_rounds): a start whose traced diagram has
more folds than the adequacy rule allows, or misses a measured point, is trained on with
orbits of the one-fold curve; checked on a model with a second fold planted above the data,
where the measured orbits cannot see it, and on the rule, the options and the report."""

import dataclasses
from types import SimpleNamespace

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tests.ude_corrections import LargeSwingFeed
from tests.ude_fixtures import write_truth_campaign
from ude_fit import UDE, identify, load, training_data
from ude_fit.analysis.diagram import _evaluate, diagram_ranges
from ude_fit.cli import main
from ude_fit.data.one_fold import fit_one_fold
from ude_fit.guide_rounds import (ROUND_GUIDES, DiagramRule, GuideRepair, GuideRound,
                                  GuideRounds, _better, constraint_weights, repair_start,
                                  round_guides)
from ude_fit.report.markdown import _guide_rounds
from ude_fit.training.guides import GUIDE_TOP
from ude_fit.training.options import DEFAULT_GUIDE_ROUNDS, FitOptions, TrainConfig

jax.config.update("jax_enable_x64", True)

# the planted model: a diagram traced three times and two short trainings on 4 + 12 orbits
pytestmark = pytest.mark.minutes(2)

TRUTH = {"hopf": 23.95, "fold": 16.82}


@pytest.fixture(scope="module")
def campaign(tmp_path_factory):
    path = tmp_path_factory.mktemp("guide_rounds") / "f.h5"
    # wide enough that the window holds the rig's fold (16.82 m/s): one fold to keep
    write_truth_campaign(path, "flutter", airspeeds=(19.0, 23.6))
    ds = load([path], "flutter")
    data = training_data(ds)
    mech, _ = identify(data, "flutter")
    return ds, data, mech


def test_the_rounds_guides_cover_the_window_where_the_data_is_silent(campaign):
    ds, *_ = campaign
    curve = fit_one_fold(ds, ds.kind.amplitude_window)
    guides = round_guides(ds, curve)
    top = max(o.amplitude for o in ds)
    grid = np.linspace(min(o.amplitude for o in ds), ds.kind.amplitude_window * top,
                       ROUND_GUIDES)
    half_step = 0.5 * (grid[1] - grid[0])
    silent = [a for a in grid if min(abs(a - o.amplitude) for o in ds) > half_step]
    assert 0 < len(silent) < ROUND_GUIDES
    np.testing.assert_allclose([o.amplitude for o in guides], silent, rtol=1e-12)
    np.testing.assert_allclose([o.parameter for o in guides],
                               curve.airspeed(np.array(silent) / top))
    assert guides.orbits[-1].amplitude == pytest.approx(ds.kind.amplitude_window * top)
    assert ds.kind.amplitude_window > GUIDE_TOP         # beyond --guide-orbits' reach


def test_a_round_takes_away_the_fold_planted_above_the_data(campaign):
    ds, data, mech = campaign
    ranges, scales = diagram_ranges(ds), np.asarray(data.y_scale)
    evaluate = lambda model: _evaluate(model, ds, ranges, scales, TRUTH, "truth")
    # LargeSwingFeed at k = 1 and this scale turns the stable branch back inside the traced
    # window, above the measured orbits, which never feel it (capped, as a saturating
    # network is: an orbit asked for at 1.4 times the top one grows instead of blowing up)
    planted = UDE(mech, LargeSwingFeed(jnp.asarray(1.0), scale=1000.0, cap=0.5))
    diag, m = evaluate(planted)
    _, m_mech = evaluate(UDE(mech))
    assert m.fold_count == m_mech.fold_count + 1
    # the rule's count where the mechanistic model has none of its own
    rule = DiagramRule(allowed=m_mech.fold_count)
    opts = FitOptions("flutter", guide_rounds=2,
                      train=TrainConfig(adam_steps=150, lbfgs_steps=60))
    guides = round_guides(ds, fit_one_fold(ds, ds.kind.amplitude_window))
    model, _, after, repair = repair_start(planted, m, diag, data=data, guides=guides,
                                           opts=opts, rule=rule,
                                           constraint_weights={}, evaluate=evaluate)
    assert isinstance(repair, GuideRepair) and repair.folds_before == m.fold_count
    assert repair.missed_before == m.summary.missed
    assert repair.kept >= 1 and after.fold_count == m_mech.fold_count, repair
    assert after.summary.missed == 0
    assert float(model.correction.k) < 0.5, float(model.correction.k)
    assert repair.rounds[repair.kept - 1].folds == after.fold_count
    assert repair.rounds[0].weight == opts.guide_weight


# the two figures the rule reads, as a diagram that misses points has them
_record = lambda folds, missed: SimpleNamespace(fold_count=folds,
                                               summary=SimpleNamespace(missed=missed))


def test_only_a_start_that_breaks_the_rule_is_trained_on(campaign):
    ds, data, mech = campaign
    ranges, scales = diagram_ranges(ds), np.asarray(data.y_scale)
    evaluate = lambda model: _evaluate(model, ds, ranges, scales, TRUTH, "truth")
    plain = UDE(mech)
    diag, m = evaluate(plain)
    assert m.fold_count == 1
    # the fit's judgement: the rule allows the mechanistic model's folds plus one
    repairs = GuideRounds(ds, data, m, FitOptions("flutter", guide_rounds=2), evaluate,
                          lambda **kw: None, False)
    assert not repairs.needed(m)
    assert repairs.needed(dataclasses.replace(m, folds=(15.0, 20.0, 22.0)))
    # none where the data needs one is left to the adequacy check (no round adds a fold)
    assert not repairs.needed(dataclasses.replace(m, folds=()))
    assert repairs.rule == DiagramRule(allowed=2)
    off = GuideRounds(ds, data, m, FitOptions("flutter", guide_rounds=0), evaluate,
                      lambda **kw: None, False)
    assert not off.needed(dataclasses.replace(m, folds=(15.0, 20.0, 22.0)))
    # a start that misses a point with its folds allowed is trained on too: a branch that
    # loses its stability between two orbits measured stable (a secondary bifurcation the
    # data does not show) misses the one inside it
    assert not repairs.needed(_record(1, 0)) and not repairs.needed(_record(2, 0))
    assert repairs.needed(_record(1, 1)) and repairs.needed(_record(0, 2))
    assert not off.needed(_record(1, 1))


def test_the_fold_rule_measures_how_far_a_diagram_is_from_it(campaign):
    ds, data, mech = campaign
    _, m = _evaluate(UDE(mech), ds, diagram_ranges(ds), np.asarray(data.y_scale), TRUTH,
                     "truth")
    with_folds = lambda *f: dataclasses.replace(m, folds=f)
    rule = DiagramRule(allowed=1)
    assert [rule.excess(with_folds(*[16.0] * n)) for n in range(4)] == [0, 0, 1, 2]
    # every missed point counts as a fold too many does
    assert [rule.excess(_record(f, k)) for f, k in ((1, 1), (0, 2), (3, 1))] == [1, 2, 3]
    # a round is better only nearer the rule and with no more points missed
    assert _better(with_folds(16.0), with_folds(16.0, 20.0, 21.0), rule)
    assert not _better(with_folds(16.0, 20.0), with_folds(16.0, 20.0), rule)
    assert not _better(_record(1, 1), _record(3, 0), rule)
    assert _better(_record(1, 1), _record(3, 1), rule)
    # a point found again with no fold added is a repair; one found at a fold's price is not
    assert _better(_record(1, 0), _record(1, 1), rule)
    assert not _better(_record(2, 0), _record(1, 1), rule)


def test_the_constraints_stay_at_their_rounds_weights():
    info = {"energy-rising_weight": 3.0, "rest-stability_weight": 0.0, "other": 1}
    assert constraint_weights(info) == {"energy-rising": 3.0, "rest-stability": 0.0}
    # every condition the rounds held (the unstable-branch one where it was asked for)
    info["unstable-branch_weight"] = 7.0
    assert constraint_weights(info)["unstable-branch"] == 7.0
    assert constraint_weights({}) == {}              # no rounds: every condition weighs 0


def test_the_rounds_are_on_by_default_where_they_apply():
    assert FitOptions("flutter").guide_rounds == DEFAULT_GUIDE_ROUNDS == 2
    for fields in (dict(system="oscillator"), dict(system="flutter", approximator="gp"),
                   dict(system="flutter", training="trajectory"),
                   dict(system="flutter", guide_orbits=8),
                   dict(system="flutter", train=TrainConfig(monotone_rounds=2))):
        assert FitOptions(**fields).guide_rounds == 0, fields
    assert FitOptions("flutter", guide_rounds=0).guide_rounds == 0


@pytest.mark.parametrize("fields, message", [
    (dict(system="oscillator", guide_rounds=2), "--guide-rounds applies to --system flutter"),
    (dict(system="flutter", guide_rounds=2, approximator="gp"), "--approximator nn"),
    (dict(system="flutter", guide_rounds=2, guide_orbits=8), "do not combine"),
    (dict(system="flutter", guide_rounds=-1), "at least 0"),
    (dict(system="flutter", guide_rounds=True), "at least 0"),
])
def test_guide_rounds_are_refused_where_they_do_not_apply(fields, message):
    with pytest.raises(ValueError, match=message):
        FitOptions(**fields)


def test_the_command_line_names_a_bad_round_count(tmp_path, capsys):
    out = tmp_path / "out"
    with pytest.raises(SystemExit) as exit_:
        main(["fit", "data.h5", "--system", "flutter", "--guide-rounds", "-1", "--out",
              str(out), "--quiet"])
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and "--guide-rounds must be at least 0, not -1" in err
    assert len(err.strip().splitlines()) == 1 and not out.exists()


def test_the_report_says_what_the_rounds_did():
    rounds = (GuideRound(0.3, 2, 0, 0.031, 0.01, ("energy-rising", "rest-stability")),
              GuideRound(0.9, 1, 0, 0.034, 0.02, ("energy-rising",)))
    repair = GuideRepair(3, 1, DiagramRule(1), rounds, 2, broken_before=("energy-rising",))
    assert repair.kept_broken == ("energy-rising",)
    rec = {"start": 2, "guide_rounds": repair.to_json()}
    text = "\n".join(_guide_rounds([{"start": 1}, rec]))
    assert "start 2: 3 folds after training, 1 allowed, 1 missed" in text
    assert "round 1 (weight 0.3): 2 folds, 0 missed, 3.10 %, breaks `--rest-stability`;" \
        in text
    assert "round 2 (weight 0.9): 1 folds, 0 missed, 3.40 %." in text
    assert "Kept round 2's model" in text and "start 1" not in text
    assert _guide_rounds([{"start": 1}]) == []
