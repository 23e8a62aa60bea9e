"""`ude-fit loop` on rigs started with effects of forms the catalogue does not list (rig
plugins under tests/plugins/: the aerofoil's at the top, the oscillator's under
oscillator/): the loop must locate the right equation and state and bring the branch error
(missed points counted) to at most a third of the mechanistic model's. Each campaign: the
rig's own true orbits held by its board at sigma = 0.02 (the aerofoil at airspeeds
19-25.5 m/s; the oscillator on the wide-band campaign's frequencies, 20-26 Hz in 2 Hz
steps, five forcing levels each).

These are slow (a campaign and a loop each, 2-10 minutes on 2 cores), so they are a
measurement run by hand, not part of the suite:
``python3 -m pytest -q -s benchmarks/locate_cases.py``. The loop runs with
``--locate-shapes``."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from tests.ude_fixtures import write_truth_campaign
from ude_fit import cli

import jax  # noqa: E402  (after the imports above, before any array)

jax.config.update("jax_enable_x64", True)       # ude_fit computes in float64 (see ude_fit docs)

PLUGINS = Path(__file__).resolve().parents[1] / "tests" / "plugins"
AIRSPEEDS = (19.0, 20.0, 21.0, 22.0, 23.0, 24.0, 25.5)
WIDE = {"freqs": (20.0, 22.0, 24.0, 26.0), "per_freq": 5}     # campaigns/oscillator_wide
CASES = {
    # plugin -> (system, equation, the located state: a state, or a velocity's coefficient
    # depending on a displacement, "h_dot(h)")
    "heave_stop": ("flutter", "heave", "h"),
    "heave_direction_damping": ("flutter", "heave", "h_dot"),
    "pitch_asymmetric": ("flutter", "pitch", "alpha"),
    "pitch_softening": ("flutter", "pitch", "alpha"),
    "heave_position_damping": ("flutter", "heave", "h_dot(h)"),
    "oscillator/contact": ("oscillator", "x", "x"),
    "oscillator/velocity_saturation": ("oscillator", "x", "x_dot"),
    "oscillator/fast_damper": ("oscillator", "x", "x_dot"),
}


def planted_states(located: str) -> list:
    """The states a located label reads: "h" -> ["h"], "h_dot(h)" -> ["h", "h_dot"]."""
    if "(" in located:
        velocity, displacement = located[:-1].split("(")
        return [displacement, velocity]
    return [located]


def write_case_campaign(path, name: str, seed: int = 0) -> None:
    """The case's sigma = 0.02 campaign (the rig started with the plugin)."""
    system = CASES[name][0]
    where = {"airspeeds": AIRSPEEDS} if system == "flutter" else WIDE
    write_truth_campaign(path, system, sigma=0.02, seed=seed, held_within=0.2,
                         plugin=f"{PLUGINS / (name + '.py')}:force", **where)


# measured 2026-11-24: located (pitch, alpha) and described as the catalogue's 5th/7th-order
# pitch stiffness, tied by BIC with a smooth saturation (both tried on the diagram: 25.1 % and
# 25.6 % after, 32.5 % before). Not a naming failure: the planted form at the planted
# threshold, given to `ude-fit refine`, reaches only 25.0 % (coefficient 19.4 against 30).
KNOWN_SHORT = {
    "pitch_softening": "named as the catalogue's pitch_poly57; error 0.77 of before (the planted "
                       "form itself, refitted: 0.77)",
}


@pytest.fixture(scope="module", params=[
    pytest.param(n, marks=pytest.mark.xfail(reason=KNOWN_SHORT[n], strict=False))
    if n in KNOWN_SHORT else n for n in CASES])
def looped(request, tmp_path_factory):
    name = request.param
    tmp = tmp_path_factory.mktemp(name.replace("/", "_"))
    path = tmp / "campaign.h5"
    write_case_campaign(path, name)
    out = tmp / "loop"
    rc = cli.main(["loop", str(path), "--system", CASES[name][0], "--locate-shapes",
                   "--out", str(out), "--quiet"])
    return name, rc, json.loads((out / "metrics.json").read_text()), out


def test_located_equation_and_state_and_error_down_to_a_third(looped):
    name, rc, m, out = looped
    _, equation, state = CASES[name]
    assert rc == 0
    e = m["effect"]
    assert e is not None, m["steps"]
    before, after = (m[k]["branch_rms_with_missed"] for k in ("before", "after"))
    print(f"{name}: {e['description']} ({e['key']}); branch RMS {100 * before:.2f} % -> "
          f"{100 * after:.2f} %")
    top = next(s for q in m["location"]["equations"] for s in q["shapes"]
               if s["significant"] and q["equation"] == equation)
    assert top["state"] == state
    assert e["equation"] == equation and set(planted_states(state)) <= set(e["states"])
    assert {"name", "terms", "coefficients", "uncertainty", "shape_class", "region"} <= set(e)
    assert after <= before / 3
    assert (out / "shapes.png").exists()
    assert "Where the residual is" in (out / "report.md").read_text()
