"""The two routes (ude_fit/discovery/routes.py): a UDE's learnt correction located and named
the way the mechanistic residual is, and the verdict on whether they agree. Corrections of
known form stand in for learnt ones (what the route reads is the correction's force on the
samples, however it was obtained); the residual route is given a planted force of known
form. The whole loop with `--ude` on a planted oscillator effect is measured by
benchmarks/loop_benchmark.py (--only located --ude)."""

from __future__ import annotations

import re

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest

from tests.ude_fixtures import write_truth_campaign
from ude_fit import UDE, load, training_data
from ude_fit.discovery.describe import describe
from ude_fit.discovery.locate import locate
from ude_fit.discovery.routes import RouteComparison, RouteFinding, compare_routes, \
    learnt_correction
from ude_fit.mechanistic_stage import identify_mechanistic
from ude_fit.models.library import band_limited, states_of
from ude_fit.report.loop_markdown import routes_section

import jax  # noqa: E402  (after the imports above, before any array)

jax.config.update("jax_enable_x64", True)       # ude_fit computes in float64 (see ude_fit docs)

STOP = 0.03          # m: inside the orbits' heave range at these airspeeds


class HeaveStop(eqx.Module):
    """A correction that is a one-sided heave stop: force -k max(h - d, 0) in heave."""
    def __call__(self, z):
        return jnp.array([-3000.0 * jnp.maximum(z[0] - STOP, 0.0), 0.0])


class PitchCubic(eqx.Module):
    """A correction acting in the pitch equation on alpha only."""
    def __call__(self, z):
        return jnp.array([0.0, -40.0 * z[1] ** 3])


@pytest.fixture(scope="module")
def setting(tmp_path_factory):
    path = tmp_path_factory.mktemp("routes") / "f.h5"
    write_truth_campaign(path, "flutter", airspeeds=(19.0, 21.0, 23.0, 25.0))
    data = training_data(load([path], "flutter"), n=32)
    mech, _ = identify_mechanistic(data, "flutter")
    S = states_of(data, "flutter")
    # the residual route's finding: a heave stop of known form, as K-harmonic orbits carry
    # it, plus noise
    rng = np.random.default_rng(0)
    f = band_limited((-3000.0 * np.maximum(S["h"] - STOP, 0.0))[:, None], 32)[:, 0]
    f = f + 0.05 * np.std(f) * rng.standard_normal(f.size)
    target = np.stack([f, np.zeros_like(f)], 1)
    residual = describe(locate(data, "flutter", target=target), S)
    return data, mech, S, residual


def test_the_learnt_correction_is_the_correction_on_every_sample(setting):
    data, mech, S, _ = setting
    U = learnt_correction(UDE(mech, HeaveStop()), data)
    assert U.shape == (S["h"].size, 2)
    assert np.max(S["h"]) > STOP + 0.005            # the stop is reached on the samples
    assert U[:, 0] == pytest.approx(-3000.0 * np.maximum(S["h"] - STOP, 0.0), abs=1e-9)
    assert np.all(U[:, 1] == 0)
    with pytest.raises(ValueError, match="no learnt correction"):
        learnt_correction(UDE(mech), data)


def test_routes_agree_when_the_correction_is_where_the_residual_is(setting):
    data, mech, S, residual = setting
    c = compare_routes(data, "flutter", UDE(mech, HeaveStop()), bootstrap=20,
                       residual_location=residual)
    assert c.residual.where == ("heave", "h")
    assert c.ude.where == ("heave", "h")
    assert c.agree
    assert "stop" in c.ude.description
    d = float(re.search(r"h > ([0-9.]+)", c.ude.description).group(1))
    assert d == pytest.approx(STOP, abs=0.02 * np.ptp(S["h"]))
    doc = c.to_json()
    assert doc["agree"] is True and doc["ude"]["state"] == "h"
    assert doc["summary"].startswith("The residual route and the UDE route agree: both "
                                     "locate an effect in heave depending on h")
    text = "\n".join(routes_section(doc))
    assert doc["summary"] in text
    assert "| residual | heave, h |" in text and "| UDE correction | heave, h |" in text


def test_routes_disagree_when_the_correction_acts_elsewhere(setting):
    data, mech, _, residual = setting
    c = compare_routes(data, "flutter", UDE(mech, PitchCubic()), bootstrap=20,
                       residual_location=residual)
    assert c.ude.where == ("pitch", "alpha")
    assert not c.agree
    assert "disagree" in c.sentence()


def test_nothing_on_either_route_agrees_and_a_half_located_finding_is_refused():
    none = RouteFinding("residual", None, None, None, None, None)
    assert RouteComparison(none, RouteFinding("UDE correction", None, None, None, None,
                                              None)).agree
    assert not RouteComparison(none, RouteFinding("UDE correction", "heave", "h", None,
                                                  None, None)).agree
    with pytest.raises(ValueError, match="both an equation and a state"):
        RouteFinding("residual", "heave", None, None, None, None)
