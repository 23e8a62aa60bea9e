"""The locate route's second stage on the aerofoil, end to end on one small campaign: a rig
started with a heave damper whose coefficient grows with the square of the displacement
(tests/plugins/heave_position_damping.py, F = -c h^2 h': no shape of one state and not a
catalogue form), its own true orbits held by its board at sigma = 0.02, then
`ude-fit loop` (its defaults). The single states' shapes do not improve the diagram, so the
loop locates the velocity's coefficient as a shape of each displacement and must find the
heave damping depending on h, name its class (quadratic) and keep it; with what the loop adds
next (the quasi-steady model's missing wake lag) the branch error must fall to at most a third
of the mechanistic model's. Two more cases of tests/located_cases.py run here the same way
(a one-sided heave stop, a nose-up-only pitch stiffness); all are measured by
benchmarks/locate_cases.py and benchmarks/loop_benchmark.py --only located."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from tests.located_cases import assert_located, loop_case
from tests.ude_fixtures import write_truth_campaign
from ude_fit import cli

import jax  # noqa: E402  (after the imports above, before any array)

jax.config.update("jax_enable_x64", True)       # ude_fit computes in float64 (see ude_fit docs)

pytestmark = pytest.mark.minutes(3.5)   # CI order: tests/conftest.py

PLUGIN = str(Path(__file__).parent / "plugins" / "heave_position_damping.py") + ":force"
AIRSPEEDS = (19.0, 20.0, 21.0, 22.0, 23.0, 24.0, 25.5)


@pytest.mark.slow
def test_a_damping_growing_with_displacement_is_found_as_a_coefficient_shape(tmp_path):
    path = tmp_path / "f.h5"
    write_truth_campaign(path, "flutter", airspeeds=AIRSPEEDS, sigma=0.02, plugin=PLUGIN,
                         held_within=0.2)
    out = tmp_path / "loop"
    rc = cli.main(["loop", str(path), "--system", "flutter", "--bootstrap", "20",
                   "--out", str(out), "--quiet"])
    assert rc == 0
    m = json.loads((out / "metrics.json").read_text())
    e = m["effect"]
    assert e is not None, m["steps"]
    assert e["equation"] == "heave" and set(e["states"]) == {"h", "h_dot"}
    assert e["key"] == "heave.h_dot(h).quadratic", e["key"]
    # the single states' candidates were tried first, on the diagram, and are in the record
    first = [s for s in m["steps"] if s["step"] == 1]
    assert first[-1]["kept"] and first[-1]["candidate"] == e["key"]
    assert any(not s["kept"] and "(" not in (s.get("candidate") or "(") for s in first)
    before, after = (m[k]["branch_rms_with_missed"] for k in ("before", "after"))
    print(f"heave position damping: {e['description']}; {100 * before:.2f} % -> "
          f"{100 * after:.2f} %")
    assert after <= before / 3


@pytest.mark.slow
@pytest.mark.parametrize("name", ["heave_stop", "pitch_asymmetric"])
def test_an_effect_outside_the_catalogue_is_located_named_and_added(tmp_path, name):
    """A one-sided heave stop (heave, h) and a nose-up-only pitch stiffness (pitch, alpha),
    each on its sigma = 0.02 campaign, through `ude-fit loop` with its defaults."""
    rc, m, out = loop_case(tmp_path, name, "--bootstrap", "20")
    assert rc == 0
    assert_located(name, m)
    assert (out / "shapes.png").read_bytes()[:4] == b"\x89PNG"
