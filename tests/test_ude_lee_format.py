"""Wind-tunnel files from a rig configuration nothing was tuned on (tests/lee_format.py):
the simulated aerofoil, in another configuration, held on its true orbits and written in the
lee2020 layout (heave in sensor volts about an offset, pitch about an encoder offset with
bursts of failed reads, the actuator in volts, the lab's file names).

Truth: the configured rig's own orbits (airspeed, stability, heave amplitude). The default
fit on such files, against the rig's Hopf and fold, is a benchmark
(benchmarks/unseen_configuration_benchmark.py): it takes minutes per start.
"""

from __future__ import annotations

import numpy as np
import pytest

from tests.lee_format import point_airspeeds, truth_of, write_lee_campaign
from ude_fit.data import load

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
        assert np.all(np.isfinite(o.coeffs)) and abs(o.coeffs[1, 0]) < 0.01


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
