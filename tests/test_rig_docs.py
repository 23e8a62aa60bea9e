"""The rig's documents against independent facts: the register table against the map
as `rig-sim registers --json` states it, and the README's socat line against the
installed socat."""

from __future__ import annotations

import json
import os
import re
import shlex
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def _cli(*args: str) -> str:
    r = subprocess.run([sys.executable, "-m", "rig_sim.cli", *args], capture_output=True, text=True,
                       cwd=REPO, timeout=60)
    assert r.returncode == 0, r.stderr
    return r.stdout


def _table_rows(markdown: str) -> tuple[list[str], list[list[str]]]:
    """(header cells, data rows' cells) of the one table in the text."""
    lines = [ln for ln in markdown.splitlines() if ln.startswith("|")]
    assert len(lines) > 3, "no register table"
    cells = [[c.strip() for c in re.split(r"(?<!\\)\|", ln.strip()[1:-1])] for ln in lines]
    header, rule, rows = cells[0], cells[1], cells[2:]
    assert all(set(c) <= {"-", ":"} for c in rule), f"second line is not the header rule: {lines[1]}"
    assert len(rule) == len(header), f"{len(header)} titles over {len(rule)} columns"
    for ln, row in zip(lines[2:], rows):
        assert len(row) == len(header), f"{len(row)} cells under {len(header)} titles: {ln}"
    return header, rows


def _row_covers(row: dict, reg: dict) -> bool:
    """Whether a (possibly folded) table row documents the register `reg`."""
    lo, _, hi = row["address"].partition("..")
    lo, hi = int(lo), int(hi or lo)
    name = row["name"].strip("`")
    pattern = re.escape(name).replace(re.escape("<c>"), r"[ab]\d+")
    return (row["table"] == reg["table"] and lo <= reg["address"] <= hi
            and re.fullmatch(pattern, reg["name"]) is not None
            and row["type"].split()[0] == reg["type"])


@pytest.mark.parametrize("source", ["docs/registers.md", "rig-sim registers", "rig-sim registers --full"])
def test_every_register_of_the_map_is_in_the_table(source):
    registers = json.loads(_cli("registers", "--format", "json"))["registers"]
    if source == "docs/registers.md":
        text = (REPO / "docs" / "registers.md").read_text()
    else:
        text = _cli(*source.split()[1:])
    header, rows = _table_rows(text)
    assert header[:4] == ["table", "address", "name", "type"], header
    rows = [dict(zip(header, r)) for r in rows]
    missing = [reg["name"] for reg in registers if not any(_row_covers(row, reg) for row in rows)]
    assert not missing, f"{source} leaves out {len(missing)} registers: {missing[:8]}"
    if source.endswith("--full"):                   # every register on a row of its own
        names = {row["name"].strip("`") for row in rows}
        assert {reg["name"] for reg in registers} <= names


def test_docs_register_table_is_current():
    assert (REPO / "docs" / "registers.md").read_text() == _cli("registers"), \
        "docs/registers.md is stale: run `rig-sim registers > docs/registers.md`"


def test_readme_socat_line_makes_two_ptys(tmp_path):
    """The README's own socat command (its link paths moved into a fresh folder) runs
    with the socat the README tells users to install and creates the pty pair."""
    if shutil.which("socat") is None:
        pytest.skip("socat is not installed (.ci/run installs it)")
    readme = (REPO / "README.md").read_text()
    # inline (`socat ...`) or a code-block line (socat ... &   # comment)
    lines = [m.strip() for m in re.findall(r"`(socat [^`]*)`", readme)
             + re.findall(r"^(socat [^&#\n]*)", readme, re.M)]
    assert lines, "README.md shows no socat command"
    argv = shlex.split(lines[0])
    links = [m for a in argv for m in re.findall(r"link=([^,\s]+)", a)]
    assert len(links) == 2, lines[0]
    moved = [str(tmp_path / Path(p).name) for p in links]
    for old, new in zip(links, moved):
        argv = [a.replace(f"link={old}", f"link={new}") for a in argv]
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 20
        while not all(os.path.exists(p) for p in moved):
            if proc.poll() is not None:
                pytest.fail(f"`{lines[0]}` exited {proc.returncode}: {proc.stderr.read()[:300]}")
            assert time.monotonic() < deadline, f"`{lines[0]}` made no pty pair in 20 s"
            time.sleep(0.05)
        for p in moved:
            assert os.path.realpath(p).startswith("/dev/pts/"), os.path.realpath(p)
    finally:
        proc.terminate()
        proc.wait(timeout=5)
