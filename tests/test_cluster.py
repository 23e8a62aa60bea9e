"""Fleets and sweeps on a real Ray cluster: a head node and a second node as local processes,
all inside a network namespace that holds only loopback (tests/cluster_scenario.py, run once
per module under ``unshare -n``). Judged against the same members run alone without Ray, the
rig's truth, and the fleet's own index. Bad fleet and sweep files need no cluster."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from cbc_controller.log import read_campaign
from tests.ray_cluster import (LONG_AIRSPEEDS, REPO, loopback_namespace_command,
                               namespace_unavailable)

pytest.importorskip("ray", reason="Ray is the optional extra `cluster`")

pytestmark = pytest.mark.minutes(4.5)   # CI order: tests/conftest.py


@pytest.fixture(scope="module")
def scenario(tmp_path_factory):
    why = namespace_unavailable()
    if why:
        pytest.skip(why)
    work = tmp_path_factory.mktemp("cluster")
    r = subprocess.run(loopback_namespace_command(
        [sys.executable, str(REPO / "tests" / "cluster_scenario.py"), str(work)]),
        capture_output=True, text=True, timeout=1500, cwd=REPO)
    assert r.returncode == 0, r.stderr[-4000:]
    res = json.loads((work / "results.json").read_text())
    res["work"] = work
    return res


def _index(folder: Path) -> dict:
    return {r["member"]: r for r in json.loads((folder / "index.json").read_text())["members"]}


def _points(path: Path) -> list[tuple]:
    return [(p["key"], p["parameter"], p["frequency"], p["amplitude"], bool(p["stable"]))
            for p in read_campaign(str(path)).points]


# ---- fleet A: two nodes, the second lost mid-run -------------------------------------------

def test_fleet_completes_after_losing_a_node_every_member_once(scenario):
    a = scenario["fleet_a"]
    assert a["rc"] == 1, a["stderr"][-3000:]        # 1: the member with the burnt coil failed
    recs = json.loads((scenario["work"] / "A" / "index.json").read_text())["members"]
    ids = [r["member"] for r in recs]
    assert sorted(ids) == sorted({"small-clean-s3", "small-cubic-s3", "small-burnt-s3",
                                  "osc23-clean-s3", "osc22-clean-s3"})
    assert len(ids) == len(set(ids))
    status = {r["member"]: r["status"] for r in recs}
    assert status.pop("small-burnt-s3") == "failed"
    errors = {r["member"]: r["error"] for r in recs if r["status"] != "completed"}
    assert set(status.values()) == {"completed"}, (status, errors)
    # the member that was running on the second node when it was killed was run again
    # elsewhere, and is in the index once, completed (its points: the next test)
    nodes, lost = scenario["nodes"], scenario["lost_member"]
    # (the failing member may be the one that was there: losing the node changes no outcome)
    outcome = {**status, "small-burnt-s3": "failed"}
    assert lost in outcome and outcome[lost] == ("failed" if lost == "small-burnt-s3"
                                                 else "completed"), (lost, status)
    assert not next(r for r in recs if r["member"] == lost)["node"].endswith(nodes["second"][:8])
    assert nodes["head"][:8] in {r["node"].split("/")[1] for r in recs}


def test_failed_rig_has_its_error_in_the_index(scenario):
    rec = _index(scenario["work"] / "A")["small-burnt-s3"]
    assert "shaker coil burnt out" in rec["error"]
    assert rec["file"] is None
    assert "small-burnt-s3: failed" in scenario["fleet_a"]["stderr"]      # progress line


def test_every_member_equals_the_same_member_run_alone(scenario, tmp_path):
    """Same campaign file, same seed, lockstep, no Ray: the same points, bit for bit."""
    folder = scenario["work"] / "A" / "members"
    for rec in _index(scenario["work"] / "A").values():
        if rec["status"] != "completed":
            continue
        alone = tmp_path / f"{rec['member']}.h5"
        r = subprocess.run([sys.executable, "-m", "cbc_controller.cli", "run",
                            str(folder / rec["member"] / "campaign.toml"), "--lockstep", "--out",
                            str(alone), "--quiet"], capture_output=True, text=True,
                           cwd=folder / rec["member"], timeout=600)
        assert r.returncode == 0, r.stderr
        ours = _points(folder / rec["member"] / "campaign.h5")
        assert ours and ours == _points(alone), rec["member"]
        assert rec["points"] == len(ours)


def test_index_reports_agreement_with_the_truth(scenario):
    idx = _index(scenario["work"] / "A")
    for name in ("small-clean-s3", "osc23-clean-s3", "osc22-clean-s3"):
        assert idx[name]["status"] == "completed", (name, idx[name]["error"])
        truth = idx[name]["truth"]
        assert truth["known"] and truth["unmatched"] == 0, truth
        assert truth["compared"] == idx[name]["points"]
        assert truth["max_error"] < 0.01, (name, truth)
    cubic = idx["small-cubic-s3"]["truth"]       # the truth with the member's hidden spring
    assert cubic["known"] and cubic["compared"] == 6 and cubic["max_error"] < 0.1, cubic
    assert idx["small-clean-s3"]["rig_seconds"] > 0


def test_rerun_of_a_finished_fleet_does_no_work(scenario):
    rerun = scenario["fleet_a_rerun"]
    assert "5 members, 5 done, 0 to run" in rerun["stderr"], rerun["stderr"]
    assert "Connected to Ray" not in rerun["stderr"]
    assert scenario["fleet_a_rerun_hashes"] == scenario["fleet_a_hashes"]
    assert len(scenario["fleet_a_hashes"]) == 4


# ---- fleet B: interrupted, then rerun ------------------------------------------------------

def test_rerun_after_an_interrupt_does_only_the_rest(scenario):
    b = scenario["fleet_b"]
    assert b["rc"] == 130, b["stderr"][-3000:]
    before = {r["member"]: r for r in scenario["fleet_b_index_after_interrupt"]["members"]}
    assert before["one-default-s5"]["status"] == "completed"
    assert before["four-default-s5"]["status"] == "interrupted", before["four-default-s5"]
    rerun = scenario["fleet_b_rerun"]
    assert rerun["rc"] == 0, rerun["stderr"][-3000:]
    assert "2 members, 1 done, 1 to run (1 resumed)" in rerun["stderr"]
    assert "one-default-s5" not in rerun["stderr"]
    h0, h1 = scenario["fleet_b_hashes"], scenario["fleet_b_rerun_hashes"]
    key = "members/one-default-s5/campaign.h5"
    assert h1[key] == h0[key]                       # the completed member was not touched
    after = _index(scenario["work"] / "B")
    assert {r["status"] for r in after.values()} == {"completed"}
    camp = read_campaign(str(scenario["work"] / "B" / after["four-default-s5"]["file"]))
    keys = [p["key"] for p in camp.points]
    assert len(camp.runs) == 2                      # resumed from its file, not restarted
    assert len(keys) == len(set(keys)) == 2 * len(LONG_AIRSPEEDS)    # a stable and an unstable
    assert {p["parameter"] for p in camp.points} == set(LONG_AIRSPEEDS)
    assert after["four-default-s5"]["truth"]["max_error"] < 0.01


# ---- the sweep --------------------------------------------------------------------------------

def test_sweep_fits_every_combination_and_each_equals_the_fit_alone(scenario, tmp_path):
    s = scenario["sweep"]
    assert s["rc"] == 0, s["stderr"][-3000:]
    out = scenario["work"] / "S"
    fits = {r["fit"]: r for r in json.loads((out / "summary.json").read_text())["fits"]}
    assert sorted(fits) == ["truth_osc-gp-periodic-s0", "truth_osc-gp-periodic-s1",
                            "truth_osc-gp-s0", "truth_osc-gp-s1"]
    assert "| truth_osc-gp-s1 |" in (out / "summary.md").read_text()
    for name, rec in fits.items():
        assert rec["status"] == "completed" and rec["branch_rms_ude"] is not None
        assert (out / rec["folder"] / "ude.eqx").is_file()
        # the same fit run alone, without Ray: the same numbers
        options = ["--approximator", "gp"] + (["--mechanistic", "periodic"]
                                              if "periodic" in name else [])
        r = subprocess.run([sys.executable, "-m", "ude_fit.cli", "fit",
                            str(scenario["work"] / "truth_osc.h5"), "--system", "oscillator",
                            "--seed", str(rec["seed"]), "--starts", "1", *options, "--out",
                            str(tmp_path / name), "--quiet"], capture_output=True, text=True,
                           timeout=900)
        assert r.returncode == 0, r.stderr
        alone = json.loads((tmp_path / name / "metrics.json").read_text())
        ours = json.loads((out / rec["folder"] / "metrics.json").read_text())
        assert ours["options"] == alone["options"]
        for model in ("mechanistic", "ude"):
            assert ours[model]["branch_rms"] == pytest.approx(alone[model]["branch_rms"],
                                                              rel=1e-9), (name, model)
        losses = [(a.get("loss"), b.get("loss"))
                  for a, b in zip(ours["starts"]["records"], alone["starts"]["records"])]
        assert len(losses) == 1 and all(a == b or a == pytest.approx(b, rel=1e-9)
                                        for a, b in losses), losses


# ---- bad files: one line naming the field, before anything starts -----------------------------

GOOD_CAMPAIGN = """[campaign]
rig = "flutter"
[parameter]
values = [18.5]
"""


@pytest.mark.parametrize("fleet, word", [
    ('[fleet]\ncampaigns = ["c.toml"]\nspeed = 3\n', "fleet.speed"),
    ('[fleet]\ncampaigns = ["c.toml"]\n[[settings]]\nlabel = "x"\ncolour = "red"\n',
     "settings[0].colour"),
    ('[fleet]\ncampaigns = ["c.toml"]\n[[settings]]\neffects = { wobble = 1.0 }\n',
     "settings[0].effects.wobble"),
    ('[fleet]\ncampaigns = []\n', "fleet.campaigns"),
    ('[fleet]\ncampaigns = ["c.toml"]\nseeds = []\n', "fleet.seeds"),
    ('[fleet]\ncampaigns = ["c.toml"]\nclock = "sundial"\n', "fleet.clock"),
    ('[fleet]\ncampaigns = ["missing.toml"]\n', "fleet.campaigns[0]"),
    ('[fleet]\ncampaigns = ["c.toml"]\n[[settings]]\nrig = "oscillator"\n', "settings[0].rig"),
])
def test_bad_fleet_file_is_a_one_line_error_naming_the_field(tmp_path, fleet, word):
    (tmp_path / "c.toml").write_text(GOOD_CAMPAIGN)
    (tmp_path / "fleet.toml").write_text(fleet)
    r = subprocess.run([sys.executable, "-m", "cbc_controller.cli", "fleet",
                        str(tmp_path / "fleet.toml"), "--out", str(tmp_path / "out")],
                       capture_output=True, text=True, cwd=REPO, timeout=120)
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and word in lines[0], r.stderr
    assert not (tmp_path / "out").exists()          # nothing started


@pytest.mark.parametrize("sweep, word", [
    ('[sweep]\nsystem = "oscillator"\ndatasets = ["d.h5"]\n[[options]]\nlearning = 3\n',
     "options[0].learning"),
    ('[sweep]\nsystem = "oscillator"\ndatasets = ["d.h5"]\n[[options]]\nstarts = 0\n',
     "options[0].starts"),
    ('[sweep]\nsystem = "oscillator"\ndatasets = []\n', "sweep.datasets"),
    ('[sweep]\nsystem = "oscillator"\ndatasets = ["d.h5"]\nseeds = []\n', "sweep.seeds"),
    ('[sweep]\nsystem = "pendulum"\ndatasets = ["d.h5"]\n', "sweep.system"),
])
def test_bad_sweep_file_is_a_one_line_error_naming_the_field(tmp_path, sweep, word):
    (tmp_path / "d.h5").write_bytes(b"")
    (tmp_path / "sweep.toml").write_text(sweep)
    r = subprocess.run([sys.executable, "-m", "ude_fit.cli", "sweep",
                        str(tmp_path / "sweep.toml"), "--out", str(tmp_path / "out")],
                       capture_output=True, text=True, cwd=REPO, timeout=120)
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and word in lines[0], r.stderr
    assert not (tmp_path / "out").exists()


def test_member_campaign_file_is_the_campaign_with_the_members_rig_settings(tmp_path):
    from cbc_controller.campaign import load_campaign
    from cbc_controller.fleet import load_fleet
    (tmp_path / "c.toml").write_text(GOOD_CAMPAIGN)
    (tmp_path / "f.toml").write_text('[fleet]\ncampaigns = ["c.toml"]\nseeds = [4, 9]\n'
                                     'clock = "time-scale"\ntime_scale = 20.0\n[[settings]]\n'
                                     'label = "fp"\nnoise = 0.02\neffects = { freeplay = 0.01 }\n')
    members = load_fleet(tmp_path / "f.toml").members()
    assert [m.id for m in members] == ["c-fp-s4", "c-fp-s9"]
    m = members[1]
    (tmp_path / "m.toml").write_text(m.campaign_toml)
    config, _ = load_campaign(tmp_path / "m.toml")
    assert config["rig"] == {"seed": 9, "noise": 0.02, "effects": ["freeplay=0.01"]}
    assert config["parameter"]["values"] == [18.5]
    assert m.clock_args == ("--time-scale", "20.0")
