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


# --- relative links in the markdown pages resolve ---------------------------------------------

FENCE = re.compile(r"^(```|~~~)")
LINK = re.compile(r"!?\[(?:[^\]\[]|\[[^\]]*\])*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
EXTERNAL = re.compile(r"^[a-z][a-z0-9+.-]*:", re.I)       # http:, https:, mailto:, ...


def _prose_lines(text: str):
    """The page's lines outside fenced code blocks, inline code removed: a link or heading
    shown as code is not one."""
    fenced = False
    for line in text.splitlines():
        if FENCE.match(line.lstrip()):
            fenced = not fenced
            continue
        if not fenced:
            yield re.sub(r"`[^`]*`", "", line)


def _anchors(page: Path) -> set[str]:
    """The anchors GitHub gives a page's headings: lower case, punctuation dropped, spaces to
    hyphens, a repeated heading numbered -1, -2, ..."""
    seen: dict[str, int] = {}
    anchors = set()
    fenced = False
    for line in page.read_text().splitlines():
        if FENCE.match(line.lstrip()):
            fenced = not fenced
            continue
        m = None if fenced else re.match(r"#{1,6}\s+(.*?)\s*#*\s*$", line)
        if not m:
            continue
        slug = re.sub(r"[^\w\- ]", "", m.group(1).lower()).replace(" ", "-")
        n = seen.get(slug, 0)
        seen[slug] = n + 1
        anchors.add(slug if n == 0 else f"{slug}-{n}")
    return anchors


def broken_links(page: Path) -> list[str]:
    """Every relative link or image of a markdown page whose file, or heading anchor in a
    markdown file, does not exist."""
    broken = []
    for line in _prose_lines(page.read_text()):
        for target in LINK.findall(line):
            if EXTERNAL.match(target):
                continue
            path, _, anchor = target.partition("#")
            dest = (page.parent / path).resolve() if path else page
            if not dest.exists():
                broken.append(f"{page.name}: {target} (no such file)")
            elif anchor and dest.suffix == ".md" and anchor not in _anchors(dest):
                broken.append(f"{page.name}: {target} (no such heading)")
    return broken


def _pages() -> list[Path]:
    return [REPO / "README.md", *sorted((REPO / "docs").rglob("*.md"))]


def test_every_relative_link_in_the_markdown_pages_resolves():
    pages = _pages()
    assert len(pages) >= 10
    broken = [b for page in pages for b in broken_links(page)]
    assert not broken, "broken links:\n" + "\n".join(broken)


def test_the_link_check_finds_missing_files_and_headings(tmp_path):
    (tmp_path / "other.md").write_text("# Other page\n\n## The `cli` options, in full\n\n## Same\n\n## Same\n")
    (tmp_path / "pic.png").write_bytes(b"")
    page = tmp_path / "page.md"
    page.write_text(
        "# Page\n\n"
        "[ok](other.md) [ok](other.md#the-cli-options-in-full) [ok](other.md#same-1) "
        "![ok](pic.png) [ok](#page) [ok](https://example.org/nowhere.md)\n"
        "`[code, not a link](missing.md)`\n"
        "```sh\n[fenced, not a link](missing.md)\n# not a heading\n```\n"
        "[bad](missing.md) [bad](other.md#nowhere) [bad](other.md#same-2) "
        "![bad](gone.png) [bad](#not-a-heading)\n")
    assert broken_links(page) == [
        "page.md: missing.md (no such file)",
        "page.md: other.md#nowhere (no such heading)",
        "page.md: other.md#same-2 (no such heading)",
        "page.md: gone.png (no such file)",
        "page.md: #not-a-heading (no such heading)",
    ]
