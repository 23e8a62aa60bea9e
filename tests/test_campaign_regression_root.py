"""The noisy-root estimator of the aerofoil plan (cbc_controller.plans.regression_root),
on synthetic measurements whose root is known: no rig, no socket."""

from __future__ import annotations

import numpy as np
import pytest

from cbc_controller.campaign import CampaignError, validate
from cbc_controller.plans.regression_root import fit_line_root, pooled_sd, root_from_blocks


def test_line_root_recovers_a_known_root_within_its_standard_error():
    rng = np.random.default_rng(0)
    root, slope, sd = 0.030, -1.3, 6e-4
    A = np.repeat([0.029, 0.0295, 0.0305, 0.031], 6)
    e = slope * (A - root) + sd * rng.standard_normal(len(A))
    f = fit_line_root(list(zip(A, e)), 0.030, 0.005)
    assert f.n == len(A) and f.slope == pytest.approx(slope, rel=0.3)
    assert abs(f.root - root) < 4 * f.se
    # the delta-method error of the root: about sd / (|slope| sqrt(n)) at a centred design
    assert f.se == pytest.approx(sd / abs(slope) / np.sqrt(len(A)), rel=0.5)
    assert fit_line_root([(0.03, 1e-4)] * 5, 0.03, 0.01) is None      # one target: no line


def test_blocks_at_the_root_are_not_biased_by_curvature():
    """e steep on one side of the root and flat on the other (an unstable cycle near its
    fold): blocks measured at the root give it without bias, whatever the slope used."""
    root = 0.021
    e_of = lambda a: -0.3 * (a - root) - 400.0 * (a - root) ** 2 * (a > root)
    samples = [(root + 1e-5, e_of(root + 1e-5)), (root - 1e-5, e_of(root - 1e-5)),
               (root, e_of(root))]
    samples += [(a, e_of(a)) for a in (root - 3e-3, root + 3e-3)] * 3   # the bracket's ends
    whole = fit_line_root(samples, root, 4e-3)
    assert abs(whole.root - root) > 1e-3          # a line through the bracket is far off
    for slope in (-0.2, -0.5, -2.0):
        f = root_from_blocks(samples, root, 5e-4, slope, block_sd=1e-6)
        assert f.root == pytest.approx(root, abs=2e-7)


def test_a_flat_slope_cannot_throw_the_root_away():
    # all blocks within noise of each other: a refitted slope near zero would put the
    # root metres away; the floor keeps the step to e / min_slope
    rng = np.random.default_rng(1)
    A = np.repeat([0.0200, 0.0203], 4)
    e = 4e-4 + 1e-5 * rng.standard_normal(len(A))
    f = root_from_blocks(list(zip(A, e)), 0.0202, 5e-4, -1e-3, block_sd=1e-5, min_slope=0.3)
    assert abs(f.slope) >= 0.3 and abs(f.root - 0.0202) < 0.002


def test_correlated_blocks_widen_the_standard_error():
    # each target's blocks share an offset (a slow drift that outlives a block): the
    # per-target means show it where the blocks' own scatter does not
    rng = np.random.default_rng(2)
    samples = []
    for k, a in enumerate(np.linspace(0.0299, 0.0301, 6)):
        offset = 5e-4 * rng.standard_normal()
        samples += [(a, -1.0 * (a - 0.03) + offset + 1e-5 * rng.standard_normal()) for _ in range(4)]
    naive = 1e-5 / np.sqrt(len(samples))
    f = root_from_blocks(samples, 0.03, 1e-4, -1.0, block_sd=1e-5)
    assert f.se > 10 * naive


def test_pooled_sd_of_repeated_measurements():
    assert pooled_sd([[1.0, 3.0], [10.0, 12.0, 14.0], [7.0]]) == pytest.approx(np.sqrt(10 / 3))
    assert pooled_sd([[1.0], [2.0]]) is None


def test_root_method_is_validated_with_a_one_line_error():
    raw = {"campaign": {"rig": "flutter"}, "parameter": {"values": [18.0]},
           "cbc": {"root_method": "newton"}}
    with pytest.raises(CampaignError) as exc:
        validate(raw, "c.toml")
    assert str(exc.value) == 'c.toml: cbc.root_method = \'newton\': must be one of "regula_falsi", "regression"'
    raw["cbc"]["root_method"] = 3
    with pytest.raises(CampaignError, match="cbc.root_method = 3: expected str"):
        validate(raw, "c.toml")
    raw["cbc"]["root_method"] = "regression"
    assert validate(raw, "c.toml")["cbc"]["root_method"] == "regression"
