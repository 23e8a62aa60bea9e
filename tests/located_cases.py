"""The planted effects of forms the catalogue does not list (issue 18): the rig plugins under
tests/plugins/ (the aerofoil's at the top, the oscillator's under oscillator/; two more put
aside under aside/), where each acts, and the sigma = 0.02 campaign each is measured on (the
rig's own true orbits held by its board: the aerofoil at airspeeds 19-25.5 m/s, the
oscillator on the wide-band campaign's frequencies, 20-26 Hz in 2 Hz steps, five forcing
levels each). tests/test_ude_locate_cases.py, benchmarks/locate_cases.py and
benchmarks/loop_benchmark.py --only located share them."""

from __future__ import annotations

import json
from pathlib import Path

from tests.ude_fixtures import write_truth_campaign

PLUGINS = Path(__file__).resolve().parent / "plugins"
AIRSPEEDS = (19.0, 20.0, 21.0, 22.0, 23.0, 24.0, 25.5)
WIDE = {"freqs": (20.0, 22.0, 24.0, 26.0), "per_freq": 5}     # campaigns/oscillator_wide
# the suite's smaller oscillator campaign (three frequencies, four levels each): the
# benchmarks run the wide one
SMALL = {"freqs": (20.0, 23.0, 26.0), "per_freq": 4}
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
# put aside before the work on issue 18 began and run only at its end: their figures are
# reported apart (loop_benchmark.py --only aside)
ASIDE = {
    "aside/heave_softening": ("flutter", "heave", "h"),
    "aside/pitch_direction_damping": ("flutter", "pitch", "alpha_dot"),
}


def planted_states(located: str) -> list:
    """The states a located label reads: "h" -> ["h"], "h_dot(h)" -> ["h", "h_dot"]."""
    if "(" in located:
        velocity, displacement = located[:-1].split("(")
        return [displacement, velocity]
    return [located]


def write_case_campaign(path, name: str, seed: int = 0, small: bool = False) -> None:
    """The case's sigma = 0.02 campaign (the rig started with the plugin); ``small``: the
    oscillator on the suite's three frequencies instead of the wide band."""
    system = {**CASES, **ASIDE}[name][0]
    write_clean_campaign(path, system, seed, plugin=f"{PLUGINS / (name + '.py')}:force",
                         small=small)


def write_clean_campaign(path, system: str, seed: int = 0, plugin: str | None = None,
                         small: bool = False) -> None:
    """The same campaign on the rig without a plugin (or with ``plugin``)."""
    where = {"airspeeds": AIRSPEEDS} if system == "flutter" else SMALL if small else WIDE
    write_truth_campaign(path, system, sigma=0.02, seed=seed, held_within=0.2,
                         plugin=plugin, **where)


def loop_case(tmp: Path, name: str, *extra: str, small: bool = False
              ) -> tuple[int, dict, Path]:
    """The case's campaign (``small``: see :func:`write_case_campaign`), then `ude-fit loop`
    with its defaults (plus ``extra``): the exit code, metrics.json and the output folder."""
    from ude_fit import cli
    path = tmp / "campaign.h5"
    write_case_campaign(path, name, small=small)
    out = tmp / "loop"
    rc = cli.main(["loop", str(path), "--system", {**CASES, **ASIDE}[name][0],
                   "--out", str(out), "--quiet", *extra])
    return rc, json.loads((out / "metrics.json").read_text()), out


def assert_located(name: str, m: dict) -> tuple[float, float]:
    """The loop located the planted equation and state, kept an effect there with every
    field the issue asks of it, and brought the branch error (missed points counted) to at
    most a third of the mechanistic model's; (before, after)."""
    _, equation, state = {**CASES, **ASIDE}[name]
    e = m["effect"]
    assert e is not None, m["steps"]
    before, after = (m[k]["branch_rms_with_missed"] for k in ("before", "after"))
    print(f"{name}: {e['description']} ({e['key']}); branch RMS {100 * before:.2f} % -> "
          f"{100 * after:.2f} %")
    top = next(s for q in m["location"]["equations"] for s in q["shapes"]
               if s["significant"] and q["equation"] == equation)
    assert top["state"] == state, top
    assert e["equation"] == equation and set(planted_states(state)) <= set(e["states"]), e
    assert {"name", "terms", "coefficients", "uncertainty", "shape_class", "region"} <= set(e)
    assert after <= before / 3
    return before, after
