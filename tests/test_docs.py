"""The generated docs are current: the CLI reference (from the parsers themselves) and the
pages the README points at exist."""

from __future__ import annotations

import importlib.util
import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def _generator():
    spec = importlib.util.spec_from_file_location("make_cli_reference",
                                                  REPO / "docs" / "make_cli_reference.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_cli_reference_is_generated_from_the_parsers_and_current(monkeypatch):
    gen = _generator()
    monkeypatch.setenv("COLUMNS", gen.WIDTH)       # restored after the test
    text = gen.render()
    assert (REPO / "docs" / "cli.md").read_text() == text, \
        "docs/cli.md is stale: run python3 docs/make_cli_reference.py"
    # every subcommand of every tool has its section, with its own usage line
    for prog, module, _ in gen.PROGRAMS:
        parser = __import__(module, fromlist=["build_parser"]).build_parser()
        for name, _sub in gen._subparsers(parser):
            assert f"### {prog} {name}\n" in text
            assert f"usage: {prog} {name}" in text


def test_readme_links_point_at_files_that_exist():
    readme = (REPO / "README.md").read_text()
    links = re.findall(r"\]\(((?:docs|campaigns)/[^)#\s]+)\)", readme)
    assert len(links) >= 5
    for link in links:
        assert (REPO / link).exists(), link
    tutorial = (REPO / "docs" / "tutorial.md").read_text()
    for img in re.findall(r"!\[[^\]]*\]\(([^)]+)\)", tutorial):
        assert (REPO / "docs" / img).exists(), img
