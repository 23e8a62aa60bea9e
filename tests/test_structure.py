"""The shape of the code: no import cycles among a package's own modules, and no module too long
to read in one sitting (STYLE.md: about 600 lines at most).

The imports are read from the source with `ast` (nothing is imported), every import counts,
those inside functions too (a lazy import is still a dependency), and relative imports are
resolved against the importing module's package.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
MAX_LINES = 600
LATER = pytest.mark.xfail(reason="ude_fit's restructuring (issue 16) is another change; the lead "
                                 "removes this mark when it lands", strict=False)
PACKAGES = ["cbc_controller", "rig_sim", pytest.param("ude_fit", marks=LATER)]


def package_modules(package: str) -> dict[str, Path]:
    """Dotted module name -> file, for every module of a package (a sub-package is its
    __init__)."""
    root = REPO / package
    out = {}
    for path in sorted(root.rglob("*.py")):
        parts = list(path.relative_to(REPO).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = path
    return out


def _resolve(module: str, is_package: bool, node: ast.ImportFrom) -> str:
    """The absolute name an ImportFrom's module part names."""
    if node.level == 0:
        return node.module or ""
    base = module.split(".")
    if not is_package:
        base = base[:-1]                       # a module's package
    if node.level > 1:
        base = base[:len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def import_graph(package: str) -> dict[str, set[str]]:
    """Module -> the package's own modules it imports."""
    modules = package_modules(package)
    graph: dict[str, set[str]] = {m: set() for m in modules}
    for name, path in modules.items():
        tree = ast.parse(path.read_text(), filename=str(path))
        for node in ast.walk(tree):
            targets = []
            if isinstance(node, ast.Import):
                targets = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = _resolve(name, path.name == "__init__.py", node)
                # `from pkg import sub` imports the module pkg.sub when there is one
                targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in modules else base
                           for a in node.names]
            for target in targets:
                # `import pkg.sub.mod` and `from pkg.sub.mod import x` depend on that module,
                # or on the nearest enclosing one of the package's
                while target and target not in modules:
                    target = target.rpartition(".")[0]
                if target and target != name:
                    graph[name].add(target)
    return graph


def import_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    cycles: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                cycles.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return cycles


def test_the_cycle_finder_finds_a_cycle_and_resolves_relative_imports(tmp_path, monkeypatch):
    """Known truth for the walker itself: a package whose a -> b -> c -> a through a relative,
    an absolute and a from-package import, and a d that only imports."""
    pkg = tmp_path / "toy"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "a.py").write_text("from .sub import b\n")
    (pkg / "sub" / "__init__.py").write_text("")
    (pkg / "sub" / "b.py").write_text("import toy.c\n")
    (pkg / "c.py").write_text("def f():\n    from toy import a\n")
    (pkg / "d.py").write_text("from .sub.b import x\nimport numpy\n")
    monkeypatch.setitem(globals(), "REPO", tmp_path)
    graph = import_graph("toy")
    assert graph["toy.a"] == {"toy.sub.b"} and graph["toy.d"] == {"toy.sub.b"}
    assert import_cycles(graph) == [["toy.a", "toy.c", "toy.sub.b"]]


@pytest.mark.parametrize("package", PACKAGES)
def test_no_import_cycles(package):
    cycles = import_cycles(import_graph(package))
    assert not cycles, f"import cycles in {package}: " + "; ".join(" <-> ".join(c) for c in cycles)


@pytest.mark.parametrize("package", PACKAGES)
def test_no_module_over_600_lines(package):
    long = {str(p.relative_to(REPO)): n for p in package_modules(package).values()
            if (n := len(p.read_text().splitlines())) > MAX_LINES}
    assert not long, f"modules over {MAX_LINES} lines: {long}"


def test_plans_do_not_import_the_engine():
    """Plans yield messages; the engine runs them (Bluesky's plans / run engine split)."""
    graph = import_graph("cbc_controller")
    runners = {"cbc_controller.engine", "cbc_controller.client"}
    bad = {m: sorted(deps & runners) for m, deps in graph.items()
           if m.startswith("cbc_controller.plans") and deps & runners}
    assert not bad, f"plans importing the engine or the client: {bad}"
