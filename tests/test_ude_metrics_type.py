"""The typed metrics results: the figures over a handful of made-up points equal a hand
computation, the JSON form has the keys metrics.json has always had, and a record that
cannot be true is refused when built."""

from __future__ import annotations

import json
import math

import pytest

from ude_fit.analysis.metrics_type import (BifurcationLocation, BranchErrors, BranchSummary,
                                           ModelMetrics, PointError)

A_MAX = 0.1          # the largest measured amplitude: the scale of the errors

# three measured orbits (airspeed, frequency, amplitude, stability); the model is 0.003 high
# at the first, 0.004 low at the second (errors 0.03 and 0.04 of A_MAX: a 3-4-5 triangle),
# and has no orbit of the measured stability at the third
FOUND_HIGH = PointError(20.0, 2.4, 0.1, True, model=0.103, error=0.03, trajectory=0.01,
                        model_stable=True)
FOUND_LOW = PointError(21.0, 2.5, 0.05, False, model=0.046, error=0.04, trajectory=0.02,
                       model_stable=False, model_parameter=21.05)
MISSED = PointError(22.0, 2.6, 0.08, True)
NOWHERE = BifurcationLocation(None)
POINT_KEYS = {"parameter", "frequency", "measured", "stable", "model", "error", "trajectory",
              "missed"}


def _flutter_metrics() -> ModelMetrics:
    errors = BranchErrors.of([FOUND_HIGH, FOUND_LOW, MISSED], A_MAX)
    loc = {"hopf": 24.5, "fold": 19.0, "folds": [19.0, 26.0], "isolas": 1,
           "isola_folds": [18.2]}
    return ModelMetrics.of(errors, loc, {"hopf": 24.0}, "given")


def test_summary_figures_equal_the_hand_computation():
    s = _flutter_metrics().summary
    assert s.branch_rms == pytest.approx(0.05 / math.sqrt(2), rel=1e-12)     # sqrt(.0025/2)
    # the missed point counted as rest: its error is its amplitude over A_MAX, 0.8
    assert s.branch_rms_with_missed == pytest.approx(
        math.sqrt((0.03 ** 2 + 0.04 ** 2 + 0.8 ** 2) / 3), rel=1e-12)
    assert s.branch_max == pytest.approx(0.04, rel=1e-12)
    assert s.missed == 1
    assert s.trajectory_rms == pytest.approx(math.sqrt((0.01 ** 2 + 0.02 ** 2) / 2), rel=1e-12)
    empty = BranchSummary.of([MISSED], A_MAX)
    assert (empty.branch_rms, empty.branch_max, empty.trajectory_rms, empty.missed) == (
        None, None, None, 1)
    assert empty.branch_rms_with_missed == pytest.approx(0.8)


def test_json_has_the_keys_metrics_json_has_and_survives_a_round_trip():
    m = _flutter_metrics()
    doc = m.to_json()
    assert json.loads(json.dumps(doc)) == doc
    assert set(doc) == {"branch_rms", "branch_rms_with_missed", "branch_max", "missed",
                        "trajectory_rms", "points", "hopf", "fold", "folds", "isolas",
                        "isola_folds"}
    high, low, missed = doc["points"]
    assert set(high) == POINT_KEYS | {"model_stable"}
    assert set(low) == POINT_KEYS | {"model_stable", "at_fold", "model_parameter"}
    assert low["at_fold"] is True and low["model_parameter"] == 21.05
    assert missed == {"parameter": 22.0, "frequency": 2.6, "measured": 0.08, "stable": True,
                      "model": None, "error": None, "trajectory": None, "missed": True}
    assert doc["hopf"] == {"model": 24.5, "reference": 24.0, "error": 0.5,
                           "reference_source": "given"}
    assert doc["fold"] == {"model": 19.0, "reference": None, "error": None,
                           "reference_source": None}
    assert (doc["folds"], doc["isolas"], doc["isola_folds"]) == ([19.0, 26.0], 1, [18.2])
    assert m.fold_count == 3 and m.families == 1
    assert {k: doc[k] for k in m.summary.to_json()} == m.summary.to_json()


def test_forced_data_keeps_its_per_frequency_figures_and_fold_table():
    at = [PointError(1.0, 22.5, 0.1, True, model=0.103, error=0.03, trajectory=0.0,
                     model_stable=True),
          PointError(2.0, 23.0, 0.05, True, model=0.046, error=0.04, trajectory=0.0,
                     model_stable=True)]
    errors = BranchErrors.of(at, A_MAX, frequencies=[22.5, 23.0])
    m = ModelMetrics.of(errors, {"hopf": None, "fold": None,
                                 "folds": {"22.5": [1.5, 3.0], "23": [2.5]}}, {}, "estimated")
    doc = m.to_json()
    assert "isolas" not in doc and doc["folds"] == {"22.5": [1.5, 3.0], "23": [2.5]}
    assert doc["per_frequency"]["22.5"]["branch_rms"] == pytest.approx(0.03)
    assert doc["per_frequency"]["23"]["branch_max"] == pytest.approx(0.04)
    assert m.fold_count == 3 and m.families == 2


@pytest.mark.parametrize("build, words", [
    (lambda: PointError(20.0, 2.4, 0.1, True, model=0.1, error=-0.01), "error"),
    (lambda: PointError(20.0, 2.4, -0.1, True), "measured"),
    (lambda: PointError(20.0, 2.4, 0.1, True, error=0.01), "missed point"),
    (lambda: PointError(20.0, 2.4, 0.1, True, model=0.1), "needs its error"),
    (lambda: PointError(math.nan, 2.4, 0.1, True), "parameter"),
    (lambda: BranchSummary(0.05, None, 0.04, 0, None), "exceeds"),
    (lambda: BranchSummary(0.05, None, 0.05, -1, None), "missed"),
    (lambda: BranchSummary(0.05, None, None, 0, None), "both"),
    (lambda: BranchErrors(BranchSummary(None, None, None, 0, None), [MISSED]), "missed"),
    (lambda: BifurcationLocation(24.0, 24.5), "source"),
    (lambda: BifurcationLocation(24.0, None, "given"), "reference"),
    (lambda: ModelMetrics(BranchErrors.of([MISSED], A_MAX), NOWHERE, NOWHERE, (19.0,)),
     "isolas"),
    (lambda: ModelMetrics(BranchErrors.of([MISSED], A_MAX), NOWHERE, NOWHERE, {"23": (2.5,)},
                          0, ()), "isola"),
])
def test_a_record_that_cannot_be_true_is_refused(build, words):
    with pytest.raises(ValueError, match=words):
        build()
