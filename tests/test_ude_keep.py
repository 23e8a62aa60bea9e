"""Which start a fit keeps (ude_fit.analysis.keep): the medoid of the adequate starts by
their Hopf and fold locations, against a hand computation; the smallest branch error where
fewer than three are adequate; the record of the rule in metrics.json and in the report's
words."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

from ude_fit.analysis.keep import KeptStart, choose_kept
from ude_fit.analysis.metrics_type import BranchErrors, ModelMetrics, PointError
from ude_fit.data.orbit import Orbit, OrbitDataset

A_MAX = 0.1
# the measured airspeeds: every Hopf point and fold below lies outside them
SPANS = {None: (19.0, 24.9)}


@dataclass
class Start:
    """What choose_kept reads of a fit's start record."""
    start: int
    judged: ModelMetrics
    adequate: bool = True
    completed: bool = True


def _metrics(error: float, hopf: float | None, fold: float | None,
             missed: int = 0, turns: tuple = ()) -> ModelMetrics:
    """``turns``: folds beyond the first (within the measured span, where a network bends
    through scattered points)."""
    found = PointError(20.0, 2.4, 0.08, True, model=0.08 + error * A_MAX, error=error,
                       trajectory=0.01, model_stable=True)
    points = [found] + [PointError(21.0 + k, 2.5, 0.05, False) for k in range(missed)]
    folds = ([] if fold is None else [fold]) + list(turns)
    return ModelMetrics.of(BranchErrors.of(points, A_MAX),
                           {"hopf": hopf, "fold": fold, "folds": folds, "isolas": 0,
                            "isola_folds": []}, {}, "given")


def _starts(rows) -> list[Start]:
    return [Start(k + 1, _metrics(*row)) for k, row in enumerate(rows)]


# the locations below are sums of quarters, so every distance is exact in binary and the
# equal ones are equal

def test_the_medoid_by_hopf_and_fold_is_kept_not_the_smallest_error():
    # start 1 fits best but puts its Hopf point 0.5-1 m/s beyond the others'
    starts = _starts([(0.010, 26.0, 18.5), (0.020, 25.0, 18.5), (0.025, 25.25, 18.5),
                      (0.030, 25.5, 18.25)])
    kept = choose_kept(starts, SPANS)
    # summed |dHopf| + |dfold| to the other three, by hand
    expect = {1: 1.0 + 0.75 + 0.75, 2: 1.0 + 0.25 + 0.75, 3: 0.75 + 0.25 + 0.5,
              4: 0.75 + 0.75 + 0.5}
    assert kept.rule == "consensus" and kept.pool == (1, 2, 3, 4)
    assert kept.landmarks == ("Hopf point", "fold")
    assert kept.distance == expect
    assert kept.start == 3


def test_equally_central_starts_are_decided_by_the_branch_error():
    # Hopf points 25, 25.5, 26, 26.5: the middle two are equally central (2.0 each)
    starts = _starts([(0.010, 25.0, 18.5), (0.025, 25.5, 18.5), (0.015, 26.0, 18.5),
                      (0.020, 26.5, 18.5)])
    kept = choose_kept(starts, SPANS)
    assert kept.distance == {1: 3.0, 2: 2.0, 3: 2.0, 4: 3.0}
    assert kept.start == 3


def test_two_adequate_starts_keep_the_smaller_error():
    # two starts cannot outvote each other
    kept = choose_kept(_starts([(0.030, 26.0, 18.5), (0.020, 25.0, 18.25)]), SPANS)
    assert kept == KeptStart(2, "smallest error")


def test_inadequate_starts_are_not_in_the_consensus():
    starts = _starts([(0.010, 26.0, 18.5), (0.020, 25.0, 18.5), (0.025, 25.25, 18.5),
                      (0.015, 25.0, 18.5)])
    assert choose_kept(starts, SPANS).start == 4     # as central as 2 and 3, closer
    starts[3].adequate = False
    kept = choose_kept(starts, SPANS)
    assert kept.pool == (1, 2, 3) and kept.distance == {1: 1.75, 2: 1.25, 3: 1.0}
    assert kept.start == 3
    starts[1].adequate = False
    assert choose_kept(starts, SPANS) == KeptStart(1, "smallest error")


def test_a_landmark_one_start_lacks_is_not_compared():
    starts = _starts([(0.010, None, 18.5), (0.020, 25.0, 18.0), (0.025, 25.25, 18.5),
                      (0.030, 27.0, 18.75)])
    kept = choose_kept(starts, SPANS)
    assert kept.landmarks == ("fold",)
    # by the fold alone starts 1 and 3 are the centre (0.75 each); start 1 fits closer
    assert kept.distance == {1: 0.75, 2: 1.75, 3: 0.75, 4: 1.25}
    assert kept.start == 1


def test_no_adequate_start_keeps_the_fewest_missed_then_the_smallest_error():
    starts = [Start(1, _metrics(0.010, 25.0, 18.0, missed=2), adequate=False),
              Start(2, _metrics(0.030, 25.0, 18.0, missed=1), adequate=False),
              Start(3, _metrics(0.020, 25.0, 18.0, missed=1), adequate=False),
              Start(4, None, adequate=False, completed=False)]
    assert choose_kept(starts, SPANS) == KeptStart(3, "not adequate")
    assert choose_kept([starts[3]], SPANS) == KeptStart(None, "none")


def test_landmarks_the_measured_orbits_bracket_are_not_compared():
    rows = [(0.010, 26.0, 18.5), (0.020, 25.0, 18.0), (0.025, 25.25, 18.75)]
    # the Hopf points inside the measured range: the folds alone decide (start 1 central)
    kept = choose_kept(_starts(rows), {None: (18.9, 26.5)})
    assert kept.landmarks == ("fold",) and kept.start == 1
    # every landmark inside: nothing left open, the smallest error
    assert choose_kept(_starts(rows), {None: (17.0, 26.5)}) == KeptStart(1, "smallest error")
    rows[0] = (0.030, 26.0, 18.5)
    assert choose_kept(_starts(rows), {None: (17.0, 26.5)}) == KeptStart(2, "smallest error")


def test_forced_landmarks_are_the_folds_outside_each_frequencys_forcing_levels():
    found = PointError(1.0, 12.0, 0.01, True, model=0.0101, error=0.01, trajectory=0.0,
                       model_stable=True)
    m = ModelMetrics.of(BranchErrors.of([found], 0.01),
                        {"hopf": None, "fold": None,
                         "folds": {"12": [0.4, 0.6, 0.9], "13": [0.5]}}, {}, "given")
    spans = {"12": (0.5, 0.8), "13": (0.2, 0.7)}
    assert m.landmarks(spans) == {"fold 1 at 12 Hz": 0.4, "fold 3 at 12 Hz": 0.9}


def test_starts_with_more_folds_than_the_fewest_are_left_out():
    # starts 1 and 4 fit closest, with a second fold inside the measured range (the network
    # bent through scattered points); by their Hopf points they would be the medoid of all
    # five (summed distances 2.0, 3.5, 2.5, 2.0, 4.0 with every first fold at 18.5)
    starts = [Start(1, _metrics(0.005, 25.5, 18.5, turns=(21.0,))),
              Start(2, _metrics(0.020, 25.0, 18.5)),
              Start(3, _metrics(0.025, 26.0, 18.5)),
              Start(4, _metrics(0.006, 25.5, 18.5, turns=(22.0,))),
              Start(5, _metrics(0.030, 26.5, 18.5))]
    kept = choose_kept(starts, SPANS)
    assert kept.pool == (2, 3, 5) and kept.folds == 1 and kept.more_folds == (1, 4)
    assert kept.distance == {2: 2.5, 3: 1.5, 5: 2.0}
    assert kept.start == 3
    assert "(starts 1, 4) were left out" in kept.describe()
    assert KeptStart.from_json(kept.to_json()) == kept
    # two one-fold starts cannot outvote each other: the smaller error of the two
    starts[2].adequate = False
    kept = choose_kept(starts, SPANS)
    assert kept == KeptStart(2, "smallest error", folds=1, more_folds=(1, 4))
    assert "smallest branch error among those with 1 fold" in kept.describe()
    # every adequate start with two folds: nothing is left out
    for s in (starts[1], starts[4]):
        s.adequate = False
    assert choose_kept(starts, SPANS) == KeptStart(1, "smallest error")


def test_the_record_round_trips_and_refuses_what_cannot_be():
    kept = choose_kept(_starts([(0.010, 26.0, 18.5), (0.020, 25.0, 18.4),
                                (0.025, 25.1, 18.6)]), SPANS)
    assert KeptStart.from_json(kept.to_json()) == kept
    assert "medoid of the 3 adequate starts" in kept.describe()
    with pytest.raises(ValueError, match="rule must be one of"):
        KeptStart(1, "best")
    with pytest.raises(ValueError, match="consensus needs 3"):
        KeptStart(1, "consensus", (1, 2), ("fold",), {1: 0.1, 2: 0.1})
    with pytest.raises(ValueError, match="exactly when"):
        KeptStart(None, "smallest error")
    with pytest.raises(ValueError, match="kept start is not among them"):
        KeptStart(1, "smallest error", folds=1, more_folds=(1,))
    # a record written before the fold count was part of the rule
    old = {k: v for k, v in kept.to_json().items() if k not in ("folds", "more_folds")}
    assert KeptStart.from_json(old) == kept


def test_the_measured_spans_are_per_branch_family():
    c = np.zeros((1, 15))
    c[0, 1] = 1e-3
    orbit = lambda p, f, n=1: Orbit(p, f, True, np.vstack([c] * n), np.zeros(15) if n == 1
                                    else None, np.nan, 1.0, "synthetic")
    flutter = OrbitDataset("flutter", tuple(orbit(v, 2.5, 2) for v in (21.0, 19.5, 24.0)),
                           ("synthetic",))
    assert flutter.parameter_spans() == {None: (19.5, 24.0)}
    forced = OrbitDataset("oscillator", (orbit(0.3, 22.5), orbit(0.9, 22.5), orbit(0.5, 23.0),
                                         orbit(0.7, 23.0), orbit(0.1, 22.5)), ("synthetic",))
    assert forced.parameter_spans() == {"22.5": (0.1, 0.9), "23": (0.5, 0.7)}
