"""The campaign file: round trip, resume, SIGKILL robustness, bad files, inspect and plot.

Synthetic documents only (no rig). The kill tests run a writer subprocess and SIGKILL it at
seeded random moments, or inside a commit at a chosen step (fault injection), then reopen.
"""

from __future__ import annotations

import json
import os
import random
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

from cbc_controller.log import (FORMAT_VERSION, CampaignFileError, CampaignWriter, completed_keys,
                                journal, read_campaign, read_timeseries, writer)
from cbc_controller.report import inspect_json, inspect_text, plot_campaign

REPO = Path(__file__).resolve().parents[1]
CHANNELS = ("response", "control", "excitation", "second")
TS_FIELDS = ("x", "x_dot", "q2", "q2_dot", "target", "control", "parameter", "phase")


# ---- synthetic documents ---------------------------------------------------------------------

def start_doc(rig="flutter", seed=7, toml=None):
    campaign = {"name": f"{rig} test", "rig": {"kind": rig},
                "plan": {"airspeeds": [12.0, 12.5, 13.0], "navg": 10, "adaptive": True},
                "tolerances": {"abs": 1e-4, "rel": 0.01}, "labels": ["a", "b"]}
    return {"campaign": campaign,
            "campaign_toml": toml if toml is not None else f'name = "{rig} test"\n[plan]\nnavg = 10\n',
            "identity": {"model": "VCL-FLUTTER-2DOF" if rig == "flutter" else "VCL-EDOSC-1DOF",
                         "firmware_version": 100, "map_version": 1,
                         "rig_kind": 0 if rig == "flutter" else 1, "sample_rate": 5000.0,
                         "ring_capacity": 2048},
            "versions": {"virtual-cbc-lab": "0.1.0", "numpy": np.__version__, "h5py": h5py.__version__},
            "rig_url": "tcp://127.0.0.1:5020", "started": "2025-03-01T10:00:00+00:00",
            "command": ["cbc-campaign", "run", "campaign.toml", "--seed", str(seed)], "seed": seed}


def point_doc(i, rig="flutter", *, n=3000, status="ok", stable=None, frequency=None,
              parameter=None, timeseries=True):
    rng = np.random.default_rng(1000 + i)
    ts = {}
    if timeseries:
        ts = {f: rng.normal(size=n) for f in TS_FIELDS}
        ts["sample"] = np.arange(n, dtype=np.int64) + 10_000 * i
    freq = frequency if frequency is not None else 3.0 + 0.01 * i
    return {
        "index": i, "key": f"{rig}/{i:03d}", "rig": rig,
        "parameter": parameter if parameter is not None else 12.0 + 0.25 * i,
        "parameter_name": "airspeed" if rig == "flutter" else "forcing_amplitude",
        "frequency": freq, "amplitude": 0.002 + 0.001 * i,
        "stable": bool(i % 2 == 0) if stable is None else stable,
        "stability_method": "branch geometry", "status": status,
        "settings": {"kp": 10.0, "kd": -0.1, "airspeed": 12.0 + 0.25 * i, "frequency": freq,
                     **{f"target_a{k}": float(rng.normal()) for k in range(8)},
                     **{f"target_b{k}": float(rng.normal()) for k in range(1, 8)}},
        "fourier": {ch: {"mean": rng.normal(size=15), "var": rng.random(15) * 1e-6}
                    for ch in CHANNELS},
        "history": [{"iteration": k, "target_amplitude": 0.001 * k, "amplitude": float(rng.random()),
                     "error": float(rng.normal()), "frequency": 3.0, "rig_time": 1.5 * k,
                     "accepted": bool(k % 2)} for k in range(5)],
        "loop": {"ticks": 1000 + i, "overruns": i, "lateness_p50_s": 1e-4, "lateness_p99_s": 5e-4,
                 "lateness_max_s": 2e-3},
        "rig_time": 100.0 + i, "wall_time": 2.5 + i, "timeseries": ts,
        "extra": {"forcing_phase": 0.25, "control_rms": 0.01 * i, "noninvasive": True,
                  "evaluations": 5, "comment": "ok", "missing": None, "list": [1, 2.5, "x"]},
    }


def stop_doc(reason="finished"):
    return {"reason": reason, "ended": "2025-03-01T11:00:00+00:00",
            "loop": {"ticks": 99_000, "overruns": 3, "lateness_p50_s": 1e-4,
                     "lateness_p99_s": 6e-4, "lateness_max_s": 4e-3}}


def write_campaign(path, points, *, rig="flutter", events=True, stop=True, **kw):
    w = CampaignWriter(path, **kw)
    w("start", start_doc(rig))
    for p in points:
        w("point", p)
    if events:
        w("fault", {"code": 4, "text": "amplitude trip", "rig_time": 55.5})
        w("link", {"event": "lost", "error": "no answer to read", "time": 1.7e9})
        w("link", {"event": "restored", "time": 1.7e9 + 2})
        w("note", {"text": "operator: door opened"})
    if stop:
        w("stop", stop_doc())
    else:
        w.close()
    return w


def assert_point_equal(got, doc, *, timeseries=True):
    for k in ("index", "key", "rig", "parameter", "parameter_name", "frequency", "amplitude",
              "stable", "stability_method", "status", "rig_time", "wall_time"):
        assert got[k] == doc[k], k
        assert type(got[k]) is type(doc[k]), k
    assert got["settings"] == doc["settings"]
    assert got["loop"] == doc["loop"]
    assert got["extra"] == doc["extra"]
    assert got["history"] == doc["history"]
    assert set(got["fourier"]) == set(doc["fourier"])
    for ch, parts in doc["fourier"].items():
        for what in ("mean", "var"):
            np.testing.assert_array_equal(got["fourier"][ch][what], parts[what])
            assert got["fourier"][ch][what].shape == (15,)
    assert got["timeseries_fields"] == sorted(doc["timeseries"])
    if timeseries:
        assert set(got["timeseries"]) == set(doc["timeseries"])
        for f, arr in doc["timeseries"].items():
            np.testing.assert_array_equal(got["timeseries"][f], arr)
            assert got["timeseries"][f].dtype == arr.dtype


# ---- round trip ------------------------------------------------------------------------------

def test_round_trip_every_field(tmp_path):
    path = tmp_path / "c.h5"
    docs = [point_doc(0), point_doc(1, status="not_converged"), point_doc(2, timeseries=False)]
    write_campaign(path, docs)
    assert not os.path.exists(str(path) + "-journal")

    c = read_campaign(path, timeseries=True)
    sd = start_doc()
    assert c.rig == "flutter" and c.format_version == FORMAT_VERSION and c.incomplete == 0
    for k in ("campaign", "campaign_toml", "identity", "versions", "rig_url", "started",
              "command", "seed"):
        assert c.metadata[k] == sd[k], k
    assert [p["seq"] for p in c.points] == [0, 1, 2]
    for got, doc in zip(c.points, docs):
        assert_point_equal(got, doc)
    assert c.points[2]["timeseries"] == {} and c.points[2]["timeseries_length"] == 0
    assert c.points[0]["timeseries_length"] == 3000

    assert [e["kind"] for e in c.events] == ["fault", "link", "link", "note"]
    assert c.events[0]["code"] == 4 and c.events[0]["text"] == "amplitude trip"
    assert c.events[0]["rig_time"] == 55.5
    assert c.events[1]["event"] == "lost" and c.events[1]["error"] == "no answer to read"
    assert c.events[1]["wall_time"] == 1.7e9 and c.events[3]["text"] == "operator: door opened"
    assert all(e["run"] == 0 for e in c.events)

    (run,) = c.runs
    assert run["started"] == sd["started"] and run["command"] == sd["command"]
    assert run["ended"] == stop_doc()["ended"] and run["stop_reason"] == "finished"
    assert run["loop"] == stop_doc()["loop"] and run["resumed"] is False
    assert c.started == sd["started"] and c.ended == stop_doc()["ended"]

    # lazily, one point at a time
    lazy = read_campaign(path)
    assert "timeseries" not in lazy.points[0]
    np.testing.assert_array_equal(lazy.timeseries(1)["x"], docs[1]["timeseries"]["x"])
    with pytest.raises(CampaignFileError):
        read_timeseries(path, 7)

    # the layout as a plain h5py user sees it
    with h5py.File(path, "r") as f:
        assert f.attrs["format"] == "cbc-campaign" and f.attrs["rig"] == "flutter"
        g = f["points/000001"]
        assert g.attrs["complete"] and g.attrs["key"] == "flutter/001"
        assert g["settings"].attrs["kp"] == 10.0
        assert g["fourier/response/mean"].shape == (15,)
        assert g["history"].dtype.names[:2] == ("iteration", "target_amplitude")
        ds = g["timeseries/x"]
        assert ds.compression == "gzip" and ds.chunks is not None
        assert g["timeseries/sample"].dtype == np.int64
        assert json.loads(f["metadata/campaign_json"].asstr()[()]) == sd["campaign"]
        assert f["events"].shape == (4,)
        assert f["runs/000"].attrs["stop_reason"] == "finished"


def test_history_that_is_not_a_table_round_trips(tmp_path):
    path = tmp_path / "c.h5"
    doc = point_doc(0)
    doc["history"] = [{"iteration": 0, "note": "bracket"}, {"iteration": 1, "error": [1, 2]}]
    write_campaign(path, [doc], events=False)
    assert read_campaign(path).points[0]["history"] == doc["history"]


# ---- resume -------------------------------------------------------------------------------------

def test_resume_appends_without_duplicating(tmp_path):
    path = tmp_path / "c.h5"
    first = [point_doc(i) for i in range(3)]
    write_campaign(path, first)
    before = read_campaign(path, timeseries=True)
    assert completed_keys(path) == {p["key"] for p in first}

    with pytest.raises(CampaignFileError, match="already exists"):
        CampaignWriter(path)("start", start_doc())

    w = CampaignWriter(path, resume=True)
    changed = start_doc(seed=8, toml='name = "changed"\n')
    changed["started"] = "2025-03-02T09:00:00+00:00"
    w("start", changed)
    more = [point_doc(i) for i in (3, 4)]
    for p in more:
        w("point", p)
    w("note", {"text": "resumed"})
    w("stop", stop_doc("finished again"))

    c = read_campaign(path, timeseries=True)
    assert [p["key"] for p in c.points] == [p["key"] for p in first + more]
    assert [p["seq"] for p in c.points] == list(range(5))
    assert [p["run"] for p in c.points] == [0, 0, 0, 1, 1]
    for got, doc in zip(c.points, first + more):
        assert_point_equal(got, doc)
    # metadata is the first run's; the new run records its own start, command and campaign
    assert c.metadata["campaign_toml"] == before.metadata["campaign_toml"]
    assert c.metadata["seed"] == 7 and c.metadata["started"] == before.metadata["started"]
    assert [r["resumed"] for r in c.runs] == [False, True]
    assert c.runs[1]["started"] == "2025-03-02T09:00:00+00:00" and c.runs[1]["seed"] == 8
    assert c.runs[1]["campaign_toml"] == 'name = "changed"\n'
    assert c.runs[1]["points_at_start"] == 3 and c.runs[1]["stop_reason"] == "finished again"
    assert c.events[-1]["run"] == 1 and len(c.events) == 5
    assert completed_keys(path) == {p["key"] for p in first + more}


def test_resume_deletes_an_incomplete_trailing_point(tmp_path):
    path = tmp_path / "c.h5"
    write_campaign(path, [point_doc(i) for i in range(2)], events=False)
    with h5py.File(path, "r+") as f:                 # what a writer killed mid-point leaves
        g = f["points"].create_group("000002")
        g.attrs["complete"] = False
        g.attrs["key"] = "flutter/002"
        g.create_dataset("junk", data=np.zeros(10))
    c = read_campaign(path)
    assert len(c.points) == 2 and c.incomplete == 1
    assert completed_keys(path) == {"flutter/000", "flutter/001"}

    w = CampaignWriter(path, resume=True)
    w("start", start_doc())
    assert w.removed_incomplete == 1
    w("point", point_doc(2))
    w.close()
    c = read_campaign(path)
    assert [p["key"] for p in c.points] == ["flutter/000", "flutter/001", "flutter/002"]
    assert [p["seq"] for p in c.points] == [0, 1, 2] and c.incomplete == 0
    assert "junk" not in c.points[2]
    assert c.runs[1]["removed_incomplete"] == 1
    assert c.runs[1]["stop_reason"] == "closed without a stop document"


def test_complete_is_set_last_and_a_failed_point_leaves_no_trace(tmp_path, monkeypatch):
    path = tmp_path / "c.h5"
    w = CampaignWriter(path)
    w("start", start_doc())
    seen = []
    real = writer._write_history

    def spy(group, rows):                            # midway through writing a point
        seen.append(bool(group.attrs["complete"]))
        real(group, rows)
    monkeypatch.setattr(writer, "_write_history", spy)
    w("point", point_doc(0))
    assert seen == [False]
    bad = point_doc(1)
    bad["timeseries"]["x"] = np.array([object(), object()], dtype=object)
    with pytest.raises(TypeError):
        w("point", bad)
    w("point", point_doc(2))
    w("stop", stop_doc())
    c = read_campaign(path)
    assert [p["key"] for p in c.points] == ["flutter/000", "flutter/002"] and c.incomplete == 0
    assert [p["seq"] for p in c.points] == [0, 1]


def test_resume_refuses_other_rig_and_missing_file(tmp_path):
    path = tmp_path / "c.h5"
    write_campaign(path, [point_doc(0)], events=False)
    w = CampaignWriter(path, resume=True)
    with pytest.raises(CampaignFileError, match="flutter campaign; the rig is a oscillator"):
        w("start", start_doc("oscillator"))
    with pytest.raises(CampaignFileError, match="no such file"):
        CampaignWriter(tmp_path / "missing.h5", resume=True)


def test_one_writer_at_a_time_and_live_reading(tmp_path):
    path = tmp_path / "c.h5"
    w = CampaignWriter(path)
    w("start", start_doc())
    w("point", point_doc(0))
    other = CampaignWriter(path, resume=True)
    with pytest.raises(CampaignFileError, match="in use"):
        other("start", start_doc())
    assert [p["key"] for p in read_campaign(path).points] == ["flutter/000"]   # while live
    w("stop", stop_doc())


# ---- SIGKILL ----------------------------------------------------------------------------------

WRITER = textwrap.dedent("""
    import os, signal, sys
    import numpy as np
    sys.path.insert(0, {repo!r})
    from cbc_controller.log import CampaignWriter, completed_keys, journal

    path, n = sys.argv[1], int(sys.argv[2])
    crash = sys.argv[3] if len(sys.argv) > 3 else ""
    resume = os.path.exists(path)
    done = completed_keys(path) if resume else set()
    if crash:                                # fault injection: die inside a commit
        stage, at_point = crash.split(":")
        state = {{"pages": 0}}
        apply_page, unlink = journal._JournaledFile._apply_page, os.unlink
        def killing_apply(self, offset, data):
            if state.get("armed"):
                if stage == "before-pages" or (stage == "mid-pages" and state["pages"] == 1):
                    os.kill(os.getpid(), signal.SIGKILL)
                state["pages"] += 1
            apply_page(self, offset, data)
        def killing_unlink(p, *a, **k):
            if state.get("armed") and stage == "before-unlink" and str(p).endswith("-journal"):
                os.kill(os.getpid(), signal.SIGKILL)
            unlink(p, *a, **k)
        journal._JournaledFile._apply_page = killing_apply
        journal.os.unlink = killing_unlink
    w = CampaignWriter(path, resume=resume, durable=False)
    w("start", {{"campaign": {{}}, "campaign_toml": "", "identity": {{"rig_kind": 1}},
                "versions": {{}}, "rig_url": "", "started": "t", "command": [], "seed": 0}})
    print("ready", len(done), flush=True)
    i = len(done)
    while True:
        if crash and i == int(at_point):
            state["armed"] = True
        ts = {{f: np.full(n, float(i)) for f in ("x", "x_dot", "q2", "target", "control")}}
        ts["sample"] = np.arange(n, dtype=np.int64) + i * n
        w("point", {{"index": i, "key": f"k{{i}}", "rig": "oscillator", "parameter": float(i),
                    "frequency": 5.0, "amplitude": 1e-3 * i, "stable": True, "status": "ok",
                    "settings": {{"s": float(i)}}, "extra": {{}},
                    "fourier": {{"response": {{"mean": np.full(15, float(i)),
                                             "var": np.full(15, 0.5)}}}},
                    "history": [{{"it": j, "v": float(i)}} for j in range(3)],
                    "timeseries": ts}})
        if i % 4 == 0:
            w("note", {{"text": f"after {{i}}"}})
        i += 1
""")


def check_killed_file(path, n):
    """Every complete point intact, in order, no gaps or duplicates; returns the count."""
    c = read_campaign(path, timeseries=True)
    assert c.incomplete == 0
    for seq, p in enumerate(c.points):
        i = int(p["parameter"])
        assert (p["seq"], p["key"], p["settings"]["s"]) == (seq, f"k{seq}", float(seq))
        assert i == seq
        np.testing.assert_array_equal(p["fourier"]["response"]["mean"], np.full(15, float(i)))
        assert [h["v"] for h in p["history"]] == [float(i)] * 3
        assert len(p["timeseries"]["x"]) == n and np.all(p["timeseries"]["x"] == i)
        np.testing.assert_array_equal(p["timeseries"]["sample"], np.arange(n) + i * n)
    assert completed_keys(path) == {f"k{j}" for j in range(len(c.points))}
    notes = [e["text"] for e in c.events if e["kind"] == "note"]
    assert len(notes) == len(set(notes))            # no event written twice either
    return len(c.points), c


def spawn_writer(tmp_path, path, n, crash=""):
    script = tmp_path / "writer.py"
    script.write_text(WRITER.format(repo=str(REPO)))
    args = [sys.executable, str(script), str(path), str(n)] + ([crash] if crash else [])
    proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    line = proc.stdout.readline()
    if not line.startswith("ready"):
        proc.kill()
        raise AssertionError(f"writer did not start: {proc.stderr.read()[-2000:]}")
    return proc, int(line.split()[1])


def test_sigkill_at_random_moments_loses_nothing(tmp_path):
    path, n = tmp_path / "killed.h5", 2000
    rnd = random.Random(20250301)
    count, runs, hot = 0, 0, 0
    for kill in range(10):
        proc, resumed_from = spawn_writer(tmp_path, path, n)
        assert resumed_from == count                # the writer saw every point we saw
        time.sleep(rnd.uniform(0.02, 0.35))
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        runs += 1
        hot += os.path.exists(str(path) + "-journal")
        now, c = check_killed_file(path, n)
        assert now >= count
        assert len(c.runs) == runs
        count = now
    assert count > 10                                # the writer did make progress between kills
    w = CampaignWriter(path, resume=True)            # a final clean resume
    w("start", start_doc("oscillator"))
    w("stop", stop_doc())
    assert not os.path.exists(str(path) + "-journal")
    assert check_killed_file(path, n)[0] == count


@pytest.mark.parametrize("stage", ["before-pages", "mid-pages", "before-unlink"])
def test_sigkill_inside_a_commit_rolls_back(tmp_path, stage):
    path, n = tmp_path / "killed.h5", 500
    proc, _ = spawn_writer(tmp_path, path, n, crash=f"{stage}:3")
    assert proc.wait(timeout=60) == -signal.SIGKILL
    journal = str(path) + "-journal"
    assert os.path.exists(journal)                   # killed with a hot journal
    count, c = check_killed_file(path, n)            # readers apply it without writing
    assert count == 3 and c.hot_journal
    assert "interrupted" in inspect_text(c)
    assert os.path.exists(journal)
    proc, resumed_from = spawn_writer(tmp_path, path, n)   # the writer plays it back
    assert resumed_from == 3
    time.sleep(0.3)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    count, c = check_killed_file(path, n)
    assert count >= 3 and c.runs[1]["recovered_journal"] is True


def test_exit_without_close_leaves_a_clean_file(tmp_path):
    path = tmp_path / "c.h5"
    code = textwrap.dedent(f"""
        import sys
        sys.path.insert(0, {str(REPO)!r})
        sys.path.insert(0, {str(REPO / 'tests')!r})
        from test_campaign_log import start_doc, point_doc
        from cbc_controller.log import CampaignWriter
        w = CampaignWriter({str(path)!r})
        w("start", start_doc())
        w("point", point_doc(0, n=100))
    """)
    subprocess.run([sys.executable, "-c", code], check=True, timeout=60)
    assert not os.path.exists(str(path) + "-journal")
    c = read_campaign(path)
    assert len(c.points) == 1 and not c.hot_journal
    assert c.runs[0]["stop_reason"] == "closed without a stop document"


def test_journal_semantics_against_a_model(tmp_path):
    """Random writes, truncations, commits and crashes (uncommitted close, or a crash while
    applying a commit) on the journaled file: reopening always yields the last commit."""
    rnd = random.Random(5)
    path = str(tmp_path / "raw.bin")
    jf = journal._JournaledFile(path, create=True, durable=False)
    model, committed = bytearray(), b""
    crashes = 0
    for step in range(400):
        op = rnd.random()
        if op < 0.55:
            off = rnd.randrange(0, len(model) + 5000)
            data = bytes(rnd.randrange(256) for _ in range(rnd.randrange(1, 9000)))
            jf.seek(off)
            jf.write(data)
            if off > len(model):
                model.extend(bytes(off - len(model)))
            model[off:off + len(data)] = data
        elif op < 0.65:
            size = rnd.randrange(0, len(model) + 100)
            jf.truncate(size)
            del model[size:]
            model.extend(bytes(size - len(model)))
        elif op < 0.85:
            jf.commit()
            committed = bytes(model)
        else:                                        # crash, then reopen
            if rnd.random() < 0.5 and jf._pages:
                def boom(self, offset, data):
                    raise KeyboardInterrupt
                jf._apply_page = boom.__get__(jf)
                with pytest.raises(KeyboardInterrupt):
                    jf.commit()
            jf.close()
            jf = journal._JournaledFile(path, create=False, durable=False)
            model = bytearray(committed)
            crashes += 1
        jf.seek(0)
        assert jf.read(len(model) + 10) == bytes(model)
    jf.commit()
    jf.close()
    assert Path(path).read_bytes() == bytes(model) and crashes > 20


# ---- bad files --------------------------------------------------------------------------------

@pytest.mark.parametrize("kind", ["text", "empty", "empty-hdf5", "other-hdf5", "truncated",
                                  "missing", "directory"])
def test_not_a_campaign_file_gives_a_one_line_error(tmp_path, kind):
    path = tmp_path / "bad.h5"
    if kind == "text":
        path.write_text("time,x\n0,1\n" * 50)
    elif kind == "empty":
        path.write_bytes(b"")
    elif kind == "empty-hdf5":
        h5py.File(path, "w").close()
    elif kind == "other-hdf5":
        with h5py.File(path, "w") as f:
            f["x"] = np.arange(10)
            f.attrs["format"] = "something-else"
    elif kind == "truncated":
        write_campaign(tmp_path / "good.h5", [point_doc(0)], events=False)
        blob = (tmp_path / "good.h5").read_bytes()
        path.write_bytes(blob[:len(blob) // 3])
    elif kind == "directory":
        path.mkdir()
    for fn in (read_campaign, completed_keys, lambda p: CampaignWriter(p, resume=True)):
        with pytest.raises(CampaignFileError) as e:
            fn(path)
        msg = str(e.value)
        assert "\n" not in msg and msg.startswith(str(path) + ": "), msg
        if kind in ("text", "empty", "empty-hdf5", "other-hdf5"):
            assert "not a campaign file" in msg


# ---- inspect and plot ---------------------------------------------------------------------------

def oscillator_campaign(path):
    docs = []
    for j, freq in enumerate((18.0, 20.0)):
        for k in range(6):
            i = len(docs)
            amp_stable = k not in (2, 3)
            docs.append(point_doc(i, "oscillator", frequency=freq + 0.001 * k, parameter=0.5 + 0.3 * k,
                                  stable=amp_stable, timeseries=False,
                                  status="fault" if (j, k) == (1, 5) else "ok"))
            docs[-1]["settings"]["frequency"] = freq
    write_campaign(path, docs, rig="oscillator")
    return read_campaign(path)


def test_inspect_json_and_text(tmp_path):
    c = oscillator_campaign(tmp_path / "osc.h5")
    rows = inspect_json(c)
    assert len(rows) == 12
    for r, p in zip(rows, c.points):
        for k in ("parameter", "frequency", "amplitude", "stable", "key", "status", "index",
                  "stability_method"):
            assert k in r
        assert isinstance(r["stable"], bool) and r["amplitude"] == p["amplitude"]
    assert rows[3]["stable"] is False and rows[0]["stable"] is True
    assert rows[11]["status"] == "fault"
    json.dumps(rows)                                  # serialisable as is
    text = inspect_text(c)
    assert "oscillator" in text and "VCL-EDOSC-1DOF" in text
    assert "12: 7 stable, 4 unstable, 1 failed" in text
    assert "forcing amplitude (m/s²)" in text and "amp (mm)" in text
    assert "1 fault, 2 link, 1 note" in text
    assert f"{0.002 * 1e3:.4f}" in text               # metres shown as millimetres


@pytest.mark.parametrize("rig", ["flutter", "oscillator"])
def test_plot_writes_a_png(tmp_path, rig):
    if rig == "oscillator":
        c = oscillator_campaign(tmp_path / "c.h5")
    else:
        write_campaign(tmp_path / "c.h5", [point_doc(i, timeseries=False) for i in range(8)])
        c = read_campaign(tmp_path / "c.h5")
    out = tmp_path / "c.png"
    plot_campaign(c, out)
    blob = out.read_bytes()
    assert blob[:8] == b"\x89PNG\r\n\x1a\n" and len(blob) > 5000
