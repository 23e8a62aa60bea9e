"""Campaign configuration: the plans' typed options, and what `cbc-campaign` refuses before it
starts a rig (a one-line error naming the field or option, exit 2, nothing written)."""

from __future__ import annotations

import dataclasses
import subprocess
import sys
from pathlib import Path

import pytest

from cbc_controller.campaign import CampaignError, validate
from cbc_controller.plans import FlutterOptions, ForcedOptions, plan_options
from rig_sim.device import register_map as M

REPO = Path(__file__).resolve().parents[1]


def run_cli(*args, timeout=60):
    return subprocess.run([sys.executable, "-m", "cbc_controller.cli", *args], capture_output=True,
                          text=True, timeout=timeout, cwd=REPO)


def flutter_raw(**sections) -> dict:
    raw = {"campaign": {"rig": "flutter"}, "parameter": {"values": [18.0]}}
    raw.update(sections)
    return raw


# ---- typed options ----------------------------------------------------------------------------

@pytest.mark.parametrize("options, message", [
    (lambda: FlutterOptions(kp="high"), "cbc.kp = 'high': expected a number"),
    (lambda: FlutterOptions(navg=2.5), "cbc.navg = 2.5: expected an integer"),
    (lambda: ForcedOptions(max_picard=-1), "cbc.max_picard = -1: must be >= 0"),
    (lambda: ForcedOptions(picard_from_control=1), "cbc.picard_from_control = 1: expected bool"),
    (lambda: FlutterOptions(record_s=float("inf")), "cbc.record_s = inf: not a finite number"),
    (lambda: FlutterOptions(root_method="newton"),
     'cbc.root_method = \'newton\': must be one of "regula_falsi", "regression"'),
    (lambda: ForcedOptions.from_table({"kq": 1.0}), "cbc.kq: unknown field for the oscillator plan"),
])
def test_options_refuse_a_bad_field_naming_it(options, message):
    with pytest.raises(ValueError) as exc:
        options()
    assert str(exc.value).startswith(message) and "\n" not in str(exc.value)


def test_rig_settings_in_the_options_are_held_to_the_register_map():
    """The register map is the datasheet: a gain the rig would refuse is refused here, with
    the rig's own range for that rig."""
    for cls, rig in ((FlutterOptions, "flutter"), (ForcedOptions, "oscillator")):
        lo, hi = M.BY_NAME["kp"].range_for(rig)
        assert cls(kp=hi).kp == hi
        with pytest.raises(ValueError) as exc:
            cls(kp=2 * hi)
        assert str(exc.value).startswith(f"cbc.kp = {2 * hi:g}: outside {lo:g}..{hi:g} ")


def test_options_are_typed_frozen_and_built_from_the_campaign():
    opts = plan_options(validate(flutter_raw(cbc={"kp": 150, "root_method": "regression"}), "c"))
    assert isinstance(opts, FlutterOptions)
    assert opts.kp == 150.0 and type(opts.kp) is float           # an integer given for a number
    assert opts.root_method == "regression" and opts.navg == FlutterOptions().navg
    with pytest.raises(dataclasses.FrozenInstanceError):
        opts.kp = 1.0
    raw = {"campaign": {"rig": "oscillator"}, "frequencies": {"values": [22.0]},
           "cbc": {"record_s": 0.5}}
    assert plan_options(validate(raw, "c")) == ForcedOptions(record_s=0.5)


def test_a_field_of_the_other_plan_is_unknown():
    with pytest.raises(CampaignError, match=r"^c.toml: cbc.fold_refine: unknown field for the "
                                            r"flutter plan \(known: "):
        validate(flutter_raw(cbc={"fold_refine": 2}), "c.toml")


# ---- the embedded rig's effects and plugin (issue 20, item 5) ---------------------------------

@pytest.mark.parametrize("rig_table, message", [
    ('effects = ["warp_drive=1"]', "rig.effects[0] = 'warp_drive=1': unknown effect for the "
                                   "flutter rig (known: freeplay, "),
    ('effects = ["freeplay=0.01", "heave_cubic"]', "rig.effects[1] = 'heave_cubic': expected "
                                                   "NAME=VALUE"),
    ('effects = ["freeplay=-0.01"]', "rig.effects[0] = 'freeplay=-0.01': value must be finite "
                                     "and >= 0"),
    ('effects = ["freeplay=0.01", "freeplay=0.02"]', "rig.effects: freeplay given twice"),
    ('plugin = "no_such_file.py:force"', "rig.plugin = 'no_such_file.py:force': file not found"),
    ('plugin = "force"', "rig.plugin = 'force': expected FILE.py:FUNC or module:FUNC"),
])
def test_validate_refuses_an_unknown_or_bad_effect(tmp_path, rig_table, message):
    toml = tmp_path / "c.toml"
    toml.write_text(f'[campaign]\nrig = "flutter"\n[rig]\n{rig_table}\n[parameter]\nvalues = [18.0]\n')
    r = run_cli("validate", str(toml))
    assert r.returncode == 2 and r.stdout == ""
    assert r.stderr.startswith(f"cbc-campaign: error: c.toml: {message}"), r.stderr
    assert len(r.stderr.strip().splitlines()) == 1
    out = tmp_path / "x.h5"
    r = run_cli("run", str(toml), "--out", str(out))
    assert r.returncode == 2 and message in r.stderr and "Traceback" not in r.stderr
    assert not out.exists()                              # refused before any rig started


def test_known_effects_pass_validation(tmp_path):
    toml = tmp_path / "c.toml"
    toml.write_text('[campaign]\nrig = "oscillator"\n[rig]\neffects = ["friction=0.01", '
                    '"cubic=1e5"]\n[frequencies]\nvalues = [22.0]\n')
    r = run_cli("validate", str(toml))
    assert r.returncode == 0 and r.stdout.strip().endswith("ok (oscillator campaign)"), r.stderr


# ---- --time-scale (issue 20, item 6) ----------------------------------------------------------

@pytest.mark.parametrize("value", ["0", "-2", "nan", "fast"])
def test_time_scale_must_be_a_positive_number(tmp_path, value):
    out = tmp_path / "x.h5"
    r = run_cli("run", str(REPO / "campaigns" / "flutter_sigma0.toml"), f"--time-scale={value}",
                "--out", str(out))
    assert r.returncode == 2, r.stderr
    line = r.stderr.strip()
    assert len(line.splitlines()) == 1 and "--time-scale" in line and repr(value) in line
    assert not out.exists()
