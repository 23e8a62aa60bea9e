"""The locate route on the shaker oscillator, end to end on one small campaign: a rig
started with a damper that engages only on fast +x motion (tests/plugins/oscillator/
fast_damper.py, not a catalogue form), its own true orbits held by its board at
sigma = 0.02, then `ude-fit loop`: the effect must be located in the x
equation on x' (not on x, where the catalogue's nearest term lives) and, added, bring the
branch error to at most a third of the mechanistic model's. Also the truth with a plugin:
the board held on a truth orbit stays on it (the plugin acts the same in both).
Two more cases of tests/located_cases.py (a one-sided contact, a saturating velocity force)
run on the same three frequencies (the benchmarks: the wide band); all are measured by benchmarks/locate_cases.py."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from tests.located_cases import assert_located, loop_case
from tests.ude_fixtures import write_truth_campaign
from ude_fit import cli

import jax  # noqa: E402  (after the imports above, before any array)

jax.config.update("jax_enable_x64", True)       # ude_fit computes in float64 (see ude_fit docs)

pytestmark = pytest.mark.minutes(2.5)   # CI order: tests/conftest.py

PLUGIN = str(Path(__file__).parent / "plugins" / "oscillator" / "fast_damper.py") + ":force"


def test_oscillator_truth_with_a_plugin_is_the_truth_with_the_same_force_built_in(tmp_path):
    """A plugin force equal to one of the rig's own effects (quadratic damping, -c|x'|x')
    gives the S-curve that effect gives: the truth integrates the plugin at every stage."""
    from rig_sim.physics.effects import load_plugin
    from rig_sim.physics.truth import oscillator_amplitude_at, oscillator_scurve
    f = tmp_path / "qd.py"
    f.write_text("import numpy as np\n\n\ndef force(t, q, qdot, params):\n"
                 "    return np.array([-0.05 * abs(qdot[0]) * qdot[0]])\n")
    plugged = oscillator_scurve(23.0, plugin=load_plugin(f"{f}:force"), amp_max=0.012)
    built_in = oscillator_scurve(23.0, effects=["quadratic_damping=0.05"], amp_max=0.012)
    clean = oscillator_scurve(23.0, amp_max=0.012)
    for Phi in (5.0, 20.0):
        a = [x for x, _ in oscillator_amplitude_at(Phi, plugged)]
        b = [x for x, _ in oscillator_amplitude_at(Phi, built_in)]
        assert a == pytest.approx(b, rel=1e-6)
        assert a != pytest.approx([x for x, _ in oscillator_amplitude_at(Phi, clean)], rel=1e-3)


@pytest.mark.slow
def test_a_damper_on_fast_motion_is_located_on_velocity_and_added(tmp_path):
    path = tmp_path / "osc.h5"
    truths = write_truth_campaign(path, "oscillator", freqs=(20.0, 23.0, 26.0), per_freq=4,
                                  sigma=0.02, plugin=PLUGIN, held_within=0.2)
    assert len(truths) >= 12           # the board holds the plugin rig's true orbits
    out = tmp_path / "loop"
    rc = cli.main(["loop", str(path), "--system", "oscillator", "--max-effects", "1",
                   "--bootstrap", "20", "--out", str(out), "--quiet"])
    assert rc == 0
    m = json.loads((out / "metrics.json").read_text())
    top = m["location"]["equations"][0]["shapes"][0]
    assert top["significant"] and top["state"] == "x_dot"
    e = m["effect"]
    assert e is not None and e["equation"] == "x" and e["states"] == ["x_dot"]
    before, after = (m[k]["branch_rms_with_missed"] for k in ("before", "after"))
    print(f"oscillator fast damper: {e['description']}; {100 * before:.2f} % -> "
          f"{100 * after:.2f} %")
    assert after <= before / 3


@pytest.mark.slow
@pytest.mark.parametrize("name", ["oscillator/contact", "oscillator/velocity_saturation"])
def test_an_effect_outside_the_catalogue_is_located_named_and_added(tmp_path, name):
    """A one-sided contact (x) and a saturating velocity force (x'), each on three
    frequencies at sigma = 0.02 (the benchmarks run the wide band), through `ude-fit loop`
    with its defaults."""
    rc, m, out = loop_case(tmp_path, name, "--bootstrap", "20", small=True)
    assert rc == 0
    assert_located(name, m)
