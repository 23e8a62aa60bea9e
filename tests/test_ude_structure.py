"""ude_fit's own shape (cycles and module sizes of all three packages: test_structure.py):
its layers import only downwards (data -> models -> training -> analysis -> guide rounds ->
mechanistic stage -> fitting -> discovery -> report -> pipeline -> cli), importing it changes
no global JAX setting, and it imports neither the rig nor the controller."""

from __future__ import annotations

import ast
import os
import subprocess
import sys

from tests.test_structure import REPO, import_graph, package_modules

# each layer may import from the layers before it, never from one after it
UDE_FIT_LAYERS = ("_precision", "_fourier", "_systems", "data", "models", "training", "analysis",
                  "model_file", "guide_rounds", "mechanistic_stage", "fitting", "discovery",
                  "report", "pipeline", "sweep", "cli")


def test_ude_fit_layers_import_only_downwards():
    def layer(mod: str) -> int | None:
        parts = mod.split(".")
        return UDE_FIT_LAYERS.index(parts[1]) if len(parts) > 1 else None

    upward = []
    for mod, deps in import_graph("ude_fit").items():
        me = layer(mod)
        if me is None:
            continue                                  # ude_fit/__init__: the public names
        upward += [(mod, d) for d in deps if layer(d) is not None and layer(d) > me]
    assert upward == []


def test_importing_ude_fit_leaves_jax_settings_alone():
    code = ("import ude_fit, ude_fit.cli, ude_fit.cli.compile_cache, jax\n"
            "assert not jax.config.jax_enable_x64, 'float64 switched on by an import'\n"
            "assert not jax.config.jax_compilation_cache_dir, 'a compile cache set by an "
            "import'\n")
    # without the test session's own cache setting (tests/conftest.py)
    env = {k: v for k, v in os.environ.items() if k != "JAX_COMPILATION_CACHE_DIR"}
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       cwd=REPO, timeout=120, env=env)
    assert r.returncode == 0, r.stderr


def test_ude_fit_imports_neither_the_rig_nor_the_controller():
    for mod, path in package_modules("ude_fit").items():
        for node in ast.walk(ast.parse(path.read_text())):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import) else
                     [node.module or ""] if isinstance(node, ast.ImportFrom) and not node.level
                     else [])
            assert not any(n.split(".")[0] in ("rig_sim", "cbc_controller") for n in names), mod
