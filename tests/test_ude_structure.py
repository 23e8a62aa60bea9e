"""The shape of the code, checked: no import cycles between a package's modules, no
module over 600 lines, ude_fit's layers importing only downwards (data -> models ->
training -> analysis -> fitting -> discovery -> report -> pipeline -> cli), and importing
ude_fit changing no global JAX setting. Generic over the package: the walk reads the
source (ast), it does not import it."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
MAX_LINES = 600

# each layer may import from the layers before it, never from one after it
UDE_FIT_LAYERS = ("_precision", "_fourier", "data", "models", "training", "analysis", "model_file", "fitting",
                  "discovery", "report", "pipeline", "cli")


def modules(package: str) -> dict[str, Path]:
    root = REPO / package
    out = {}
    for path in sorted(root.rglob("*.py")):
        rel = path.relative_to(REPO).with_suffix("")
        parts = list(rel.parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = path
    return out


def _resolve(module: str, is_package: bool, node: ast.ImportFrom) -> str:
    if node.level == 0:
        return node.module or ""
    base = module.split(".") if is_package else module.split(".")[:-1]
    base = base[:len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def imports(package: str) -> dict[str, set[str]]:
    """Module -> the package's modules it imports (at any depth in the file)."""
    mods = modules(package)
    graph = {}
    for name, path in mods.items():
        deps = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = _resolve(name, path.name == "__init__.py", node)
                targets = [base] + [f"{base}.{a.name}" for a in node.names]
            else:
                continue
            deps.update(t for t in targets if t in mods and t != name)
        graph[name] = deps
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Every strongly connected component of more than one module (Tarjan)."""
    index, low, stack, on, out = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in graph:
        if v not in index:
            visit(v)
    return out


@pytest.mark.parametrize("package", ["ude_fit"])
def test_no_import_cycles(package):
    assert cycles(imports(package)) == []


@pytest.mark.parametrize("package", ["ude_fit"])
def test_no_module_over_600_lines(package):
    long = {name: n for name, path in modules(package).items()
            if (n := len(path.read_text().splitlines())) > MAX_LINES}
    assert long == {}


def test_ude_fit_layers_import_only_downwards():
    def layer(mod: str) -> int | None:
        parts = mod.split(".")
        return UDE_FIT_LAYERS.index(parts[1]) if len(parts) > 1 else None

    upward = []
    for mod, deps in imports("ude_fit").items():
        me = layer(mod)
        if me is None:
            continue                                  # ude_fit/__init__: the public names
        upward += [(mod, d) for d in deps if layer(d) is not None and layer(d) > me]
    assert upward == []


def test_the_cycle_finder_finds_a_cycle():
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": set()}) == []


def test_importing_ude_fit_leaves_jax_settings_alone():
    code = ("import ude_fit, ude_fit.cli, jax\n"
            "assert not jax.config.jax_enable_x64, 'float64 switched on by an import'\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       cwd=REPO, timeout=120)
    assert r.returncode == 0, r.stderr


def test_ude_fit_imports_neither_the_rig_nor_the_controller():
    for mod, path in modules("ude_fit").items():
        for node in ast.walk(ast.parse(path.read_text())):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import) else
                     [node.module or ""] if isinstance(node, ast.ImportFrom) and not node.level
                     else [])
            assert not any(n.split(".")[0] in ("rig_sim", "cbc_controller") for n in names), mod
