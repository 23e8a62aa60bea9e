"""Issue 17's invasive criterion on campaigns the CBC controller holds itself: the flutter
plan (``cbc-campaign run``, the embedded rig in lockstep, noise-free) at 17-23 m/s, once at
its default tolerances and once with the root accepted at ``tolerance_rel = 0.05``, what "a
campaign held with loose tolerances" is on the wire (tests/invasive_cases.write_cbc_cases).

Truth: the rig's own open-loop orbits at the same airspeeds (Hopf 23.95, fold 16.82 m/s).
The default fit, one start, seed 0, on each campaign: the loose one with the recorded
control as an input must recover the open-loop diagram as well as the fit to the
default-tolerance campaign does (Hopf and fold within 0.1 m/s of that fit's, branch error
against the truth at most 1.5 times its), and without the control do measurably worse.
benchmarks/invasive_benchmark.py --cbc prints the same figures for other seeds and starts.
"""

from __future__ import annotations

import pytest

from tests.invasive_cases import criterion, criterion_figures, fit_cases
from ude_fit.report.markdown import render

import jax  # noqa: E402  (after the imports above, before any array)

pytestmark = pytest.mark.minutes(4)   # CI order: tests/conftest.py

jax.config.update("jax_enable_x64", True)

TOLERANCE = 0.05        # the plan's tolerance_rel for the loose campaign (default 0.01)


@pytest.fixture(scope="module")
def fits(tmp_path_factory):
    out = fit_cases(tmp_path_factory.mktemp("cbc"), TOLERANCE, cbc=True)
    for name, (r, m, _, _) in out.items():
        assert r.ude is not None and m is not None, name
    return out


def test_the_control_input_recovers_the_non_invasive_fit(fits):
    """Measured (seed 0): the default-tolerance campaign 0.095 %, Hopf 23.901, fold
    16.779 m/s; the loose one with the control 0.113 % (1.19 times), 23.918, 16.784; without
    the control 0.275 % (2.4 times the fit with it). Every truth orbit found by all three."""
    held, ctrl, plain = (fits[k][1] for k in ("held", "loose+control", "loose"))
    for m in (held, ctrl, plain):
        assert m.errors.summary.missed == 0
        assert m.hopf.model is not None and m.fold.model is not None
    said = criterion(*(criterion_figures(m.to_json()) for m in (held, ctrl, plain)))
    assert said["met"], said
    assert said["without_control_ratio"] >= 1.5 * said["error_ratio"], said


def test_the_report_says_which_points_the_loose_campaign_held_invasively(fits):
    """The loose campaign's targets lie off their responses by what the root search left
    (largest 1.3 % against the default tolerance's 0.09 %, measured): every point's
    holding is in metrics.json and the report's table, and the loose campaign's largest
    target mismatch is at least five times the default-tolerance campaign's."""
    def mismatches(name):
        doc = fits[name][0].to_json()
        holdings = [p["holding"] for p in doc["data"]["point_records"]]
        assert len(holdings) == doc["data"]["points"] == 14
        assert all(h is not None and h["target_mismatch"] is not None for h in holdings)
        return doc, [h["target_mismatch"] for h in holdings]
    _, held = mismatches("held")
    doc, loose = mismatches("loose+control")
    assert max(loose) >= 5 * max(held), (loose, held)
    r = fits["loose+control"][0]
    text = render({**doc, "version": "test", "written": "now", "command": "fit",
                   "options": r.options.to_json()}, {})
    assert "| target vs response | invasive |" in text
    for point in doc["data"]["point_records"]:
        assert f"| `{point['source']}` | {point['parameter']:.4g} |" in text, point


def test_without_the_control_nothing_is_judged_under_it(fits):
    """The loose campaign fitted without the control as an input: no gain in the
    identification, the starts judged by the open-loop diagram, no orbits under the control
    and no held sides anywhere in metrics.json, and ``ude-fit fit`` prints one line (the
    fit with the control: its orbits under the control too)."""
    from ude_fit.cli.fit import summary
    plain = fits["loose"][0].to_json()
    assert "control" not in plain["mechanistic"]["identification"]
    assert plain["starts"]["criterion"]["judged_by"] == "the diagram"
    assert "controlled" not in plain["mechanistic"] and "controlled" not in plain["ude"]
    assert all("controlled" not in x for x in plain["starts"]["records"])
    assert len(summary(fits["loose"][0], 1)) == 1
    with_u = fits["loose+control"][0].to_json()
    assert with_u["starts"]["criterion"]["judged_by"] == "the orbits under the recorded control"
    assert "controlled" in with_u["ude"] and len(summary(fits["loose+control"][0], 1)) >= 2
