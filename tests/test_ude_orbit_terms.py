"""Each orbit's parts of the periodic objective (ude_fit.training.losses.orbit_terms), against
the aerofoil model's own limit cycles traced by the continuation: an exact orbit fits and
closes, and its stability indicator has the sign of the traced stability. The stability
tests themselves against monodromy matrices with planted Floquet multipliers."""
from __future__ import annotations

import dataclasses

import jax  # noqa: E402
import jax.numpy as jnp
import numpy as np
import pytest

from ude_fit import duffing7, flutter_qs
from ude_fit.models.mechanistic import _exterior_square
from ude_fit.training.losses import orbit_terms, orbit_unknowns, periodic_objective
from ude_fit.training.options import TrainConfig
from tests.model_orbits import traced_orbits

jax.config.update("jax_enable_x64", True)

SAMPLES, SUBSTEPS = 50, 4         # 200 RK4 steps a period: the continuation's own


@pytest.fixture(scope="module")
def traced():
    """One unstable orbit (between the Hopf point and the fold) and one stable one beyond
    it."""
    def middles(branch):
        unstable, stable = np.flatnonzero(~branch.stable), np.flatnonzero(branch.stable)
        return unstable[len(unstable) // 2], stable[len(stable) // 2]
    return traced_orbits(SAMPLES, SUBSTEPS, middles)


def test_an_exact_orbit_fits_and_closes_with_its_traced_stability(traced):
    model, data, label = traced
    cfg = TrainConfig(substeps=SUBSTEPS).for_system("flutter")
    t = orbit_terms(model, orbit_unknowns(data, True), data, cfg)
    assert np.all(np.asarray(t.fit) < 1e-20)
    assert np.all(np.asarray(t.closure) < 1e-12)     # the continuation's Newton tolerance
    assert np.all(np.sign(np.asarray(t.indicator)) == label)
    # the mechanistic model's orbits leave the circle, where they do, through +1 only
    assert np.all(np.asarray(t.secondary) > 0)
    assert np.all(np.asarray(t.prior) == 0.0)


def test_the_objective_is_made_of_the_terms(traced):
    """The periodic objective is each orbit's misfit, closure and stability hinge, from the
    same terms; an orbit labelled against its stability pays the hinge."""
    model, data, label = traced
    cfg = TrainConfig(substeps=SUBSTEPS).for_system("flutter")
    params = orbit_unknowns(data, True)
    params["dy0"] = params["dy0"] + 1e-3            # off the orbits, so every term counts
    wrong = data.__class__(data.ys, data.qdd, data.period, data.drive, -data.label,
                           data.y_scale, data.amp_max)
    t = orbit_terms(model, params, wrong, cfg)
    hinge = np.maximum(cfg.stability_margin + label * np.asarray(t.indicator), 0.0) ** 2
    assert np.all(hinge > 0)
    # the orbit labelled stable pays for its other multipliers too, where they are within
    # the margin of the circle (these are not: the term is there and costs nothing)
    held = np.where(-label > 0, np.sum(np.maximum(
        cfg.stability_margin - np.asarray(t.secondary), 0.0) ** 2, axis=-1), 0.0)
    hinge = hinge + held
    expected = np.mean(np.asarray(t.fit) + cfg.closure_weight * np.asarray(t.closure)
                       + cfg.stability_weight * hinge)
    assert float(periodic_objective(model, params, wrong, cfg)) == pytest.approx(expected,
                                                                                rel=1e-12)


def test_each_orbit_is_held_at_its_own_margin(traced):
    """With per-orbit margins (analysis.margins) the hinge of an orbit is measured from its
    own margin; nan stands for the configured one."""
    model, data, label = traced
    cfg = TrainConfig(substeps=SUBSTEPS).for_system("flutter")
    params = orbit_unknowns(data, True)
    t = orbit_terms(model, params, data, cfg)
    held = label * np.asarray(t.indicator)            # > 0: both on their labelled side
    assert np.all(held > cfg.stability_margin)       # the constant margin costs nothing
    own = dataclasses.replace(data, margin=jnp.asarray([2 * held[0], np.nan]))
    plain = float(periodic_objective(model, params, data, cfg))
    expected = plain + cfg.stability_weight * held[0] ** 2 / 2      # mean over 2 orbits
    assert float(periodic_objective(model, params, own, cfg)) == pytest.approx(expected,
                                                                              rel=1e-9)


# ---------------------------------------------------------------------------------------
# the stability tests against planted multipliers
# ---------------------------------------------------------------------------------------

def _planted(trivial: bool, real=(), pairs=(), seed=0):
    """A monodromy matrix with the given real multipliers and complex pairs (r, angle), and
    the trivial multiplier 1 first where ``trivial``, in a random basis."""
    blocks = ([1.0] if trivial else []) + list(real)
    n = len(blocks) + 2 * len(pairs)
    D = np.zeros((n, n))
    D[np.arange(len(blocks)), np.arange(len(blocks))] = blocks
    for k, (r, th) in enumerate(pairs):
        i = len(blocks) + 2 * k
        D[i:i + 2, i:i + 2] = r * np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
    P = np.random.default_rng(seed).normal(size=(n, n))
    return jnp.asarray(P @ D @ np.linalg.inv(P))


def _outside(M, trivial: bool) -> bool:
    """Whether a non-trivial multiplier of M lies outside the unit circle (numpy's
    eigenvalues, the trivial one removed)."""
    mu = np.linalg.eigvals(np.asarray(M))
    if trivial:
        mu = np.delete(mu, np.argmin(np.abs(mu - 1.0)))
    return bool(np.max(np.abs(mu)) > 1.0)


def test_the_exterior_square_has_the_products_of_pairs():
    M = np.random.default_rng(3).normal(size=(5, 5))
    mu = np.linalg.eigvals(M)
    products = np.array([mu[i] * mu[j] for i in range(5) for j in range(i + 1, 5)])
    got = np.linalg.eigvals(np.asarray(_exterior_square(jnp.asarray(M))))
    assert np.allclose(np.sort_complex(got), np.sort_complex(products), atol=1e-9)


@pytest.mark.parametrize("mech,trivial", [(flutter_qs(), True), (duffing7(), False)])
def test_each_way_out_of_the_circle_changes_one_tests_sign(mech, trivial):
    """A real multiplier through -1 turns the period-doubling test negative, a complex pair
    across the circle the torus test; the fold test (stability_indicator) stays positive
    through both, which is why the others exist. A multiplier through +1 is the fold test's
    alone."""
    extra = (0.87,) if trivial else ()    # the self-excited branch's amplitude multiplier
    for mu in (-0.9, -0.99, -1.01, -1.2):                  # period doubling
        M = _planted(trivial, extra + (mu, 0.3))
        flip, torus = np.asarray(mech.secondary_indicators(M))
        assert (flip < 0) == _outside(M, trivial) == (mu < -1)
        assert torus > 0 and float(mech.stability_indicator(M)) > 0
    for r in (0.9, 0.99, 1.01, 1.1):                       # a pair across the circle
        M = _planted(trivial, extra, pairs=((r, 2.0),))
        flip, torus = np.asarray(mech.secondary_indicators(M))
        assert (torus < 0) == _outside(M, trivial) == (r > 1)
        assert flip > 0 and float(mech.stability_indicator(M)) > 0
    M = _planted(trivial, (1.1, 0.3) if trivial else (1.1,), pairs=((0.5, 1.0),))
    assert float(mech.stability_indicator(M)) < 0
    assert float(mech.secondary_indicators(M)[0]) > 0


def test_the_tests_are_the_multipliers_products():
    """Self-excited: prod(1 + mu) and prod over pairs (1 - mu_i mu_j), over the
    non-trivial multipliers; forced: over all of them."""
    real, pair = (0.6, -0.4), (0.7, 1.3)
    mus = np.array(list(real) + [pair[0] * np.exp(1j * pair[1]), pair[0] * np.exp(-1j * pair[1])])
    flip = np.prod(1 + mus).real
    torus = np.prod([1 - mus[i] * mus[j] for i in range(4) for j in range(i + 1, 4)]).real
    got = np.asarray(flutter_qs().secondary_indicators(_planted(True, real, (pair,))))
    assert np.allclose(got, [flip, torus], rtol=1e-9)
    got = np.asarray(duffing7().secondary_indicators(_planted(False, real, (pair,))))
    assert np.allclose(got, [flip, torus], rtol=1e-9)


def test_a_stable_label_pays_for_a_multiplier_past_minus_one(traced):
    """The periodic objective's stability term for an orbit labelled stable: the fold
    test's hinge plus the two others' at the configured margin, on the self-excited system;
    an orbit labelled unstable pays for the fold test's alone."""
    model, data, label = traced
    cfg = TrainConfig(substeps=SUBSTEPS).for_system("flutter")
    params = orbit_unknowns(data, True)
    t = orbit_terms(model, params, data, cfg)
    # the stable orbit's other multipliers asked to sit further in than they do
    stable = np.asarray(t.secondary)[label > 0]
    wide = dataclasses.replace(cfg, stability_margin=float(np.max(stable)) + 1)
    t = orbit_terms(model, params, data, wide)
    fold = np.maximum(wide.stability_margin - label * np.asarray(t.indicator), 0.0) ** 2
    # (an unstable orbit's torus test is +inf: the fold test has it unstable already)
    others = np.sum(np.maximum(wide.stability_margin - np.asarray(t.secondary), 0.0) ** 2,
                    axis=-1)
    expected = np.mean(np.asarray(t.fit) + wide.closure_weight * np.asarray(t.closure)
                       + wide.stability_weight * (fold + np.where(label > 0, others, 0.0)))
    assert float(periodic_objective(model, params, data, wide)) == pytest.approx(expected,
                                                                                rel=1e-12)
