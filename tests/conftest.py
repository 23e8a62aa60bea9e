"""Shared fixtures: real rig-sim service processes, socat pty pairs."""

from __future__ import annotations

import gc
import os
import sys
import shutil
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

# XLA executables kept on disk and shared by the session's workers, modules and the
# subprocesses they start (which inherit the environment): each module's fits compile the
# same shooting losses, and a module's in-memory cache is let go after it (below). The
# folder is the user's cache, not the clone, so a later run of the suite on the same
# machine (CI clones afresh every time) loads what an earlier one compiled: an executable is
# found again only for the same program, JAX version and machine, so results are the same
# as compiling afresh. Every executable is kept however fast it compiled; the size bound
# (least recently used go first) turns on JAX's file lock, so two workers writing one entry
# cannot tear it. Set before anything imports jax, which reads these at import.
def _compiled_code_folder() -> Path:
    # the XDG rule of ude_fit.cli.compile_cache.cache_dir, written out here because
    # importing ude_fit imports jax, which must come after these settings
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    where = Path(base) / "ude-fit" / "xla-tests"
    try:
        where.mkdir(parents=True, exist_ok=True)
        return where
    except OSError:                 # no writable cache folder: this run's own, in the clone
        return REPO / ".pytest_cache" / "jax"


if not os.environ.get("JAX_COMPILATION_CACHE_DIR"):
    os.environ["JAX_COMPILATION_CACHE_DIR"] = str(_compiled_code_folder())
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")
os.environ.setdefault("JAX_COMPILATION_CACHE_MAX_SIZE", str(2 << 30))

from ude_fit.cli.compile_cache import mend_entries  # noqa: E402  (after the cache settings)
from rig_sim.harness import PtyPair, RigProcess  # noqa: E402

# a run killed between an entry's two writes leaves it without its access-time record, and
# then nothing new is kept (ude_fit/cli/compile_cache.py); the folder outlives the run
_COMPILED_CODE = Path(os.environ["JAX_COMPILATION_CACHE_DIR"])
if _COMPILED_CODE.is_dir():
    mend_entries(_COMPILED_CODE)


@pytest.fixture
def rig_process():
    """Factory: start rig-sim with the given CLI args (always --port 0 unless given)."""
    started: list[RigProcess] = []

    def start(*args: str, stderr_file=None) -> RigProcess:
        if "--port" not in args and "--no-tcp" not in args:
            args = (*args, "--port", "0")
        p = RigProcess(*args, cwd=REPO, stderr_file=stderr_file)
        started.append(p)
        return p

    yield start
    for p in started:
        p.stop()


@pytest.fixture
def pty_pair(tmp_path):
    if shutil.which("socat") is None:
        pytest.skip("socat is not installed (.ci/run installs it)")
    pair = PtyPair(tmp_path)
    yield pair
    pair.close()


@pytest.fixture(scope="session")
def lee2020_dir() -> Path:
    """The lee2020 wind-tunnel data (a directory holding model2/): $LEE2020_DIR, else
    <repo>/../shared/data/lee2020, else /work/shared/data/lee2020. The data is never copied
    into the repository, so where none of these exists the tests that need it skip."""
    candidates = [os.environ.get("LEE2020_DIR"), REPO.parent / "shared" / "data" / "lee2020",
                  "/work/shared/data/lee2020"]
    for c in candidates:
        if c and (Path(c) / "model2").is_dir():
            return Path(c)
    pytest.skip("lee2020 data not found (set LEE2020_DIR to the directory holding model2/; "
                f"looked in: {', '.join(str(c) for c in candidates if c)})")


@pytest.fixture(scope="session")
def flutter_truth() -> dict:
    """The aerofoil rig's true Hopf and (lowest) fold airspeeds, from its own continuation."""
    from tests.ude_fixtures import flutter_branch
    br = flutter_branch()
    return {"hopf": br.hopf[0], "fold": min(f["V"] for f in br.folds)}


def pytest_configure(config):
    config.addinivalue_line(
        "markers", "minutes(n): the module's expected wall time on 2 shared cores; CI starts "
        "the longest modules first so that its two workers finish together")


def pytest_collection_modifyitems(config, items):
    """Longest modules first (their ``minutes`` mark; unmarked ones are short), the order
    within a module and among equals kept: with ``--dist loadfile --no-loadscope-reorder``
    the workers take whole modules in this order, so a long module never starts last and
    leaves the other worker idle (the default orders them by their number of tests)."""
    def minutes(item):
        mark = item.get_closest_marker("minutes")
        return mark.args[0] if mark else 0.0
    items.sort(key=lambda item: -minutes(item))
    for item in items:
        _timeout_for_its_module(item, minutes(item))


# How much slower than the machine the ``minutes`` marks were measured on a CI machine may
# be: the same commit's suite took 30 min on one machine of this kind and 74 on another,
# where its one-start fits' steps were 2.4 times slower; on that machine the module
# fixtures took up to 3.2 times their marks (test_ude_control_input: 574 s, marked 3 min).
SLOWER_MACHINE = 6.0


def _timeout_for_its_module(item, minutes: float) -> None:
    """A test's time limit (pytest-timeout) counts its module fixture's fits, which the first
    test of a long module pays: such a test gets its module's expected time on a machine
    ``SLOWER_MACHINE`` times slower, if that is longer than the suite's limit. The limit is
    there to stop a hang, not to time the fits (benchmarks do that); a test's own
    ``timeout`` mark is kept."""
    if item.get_closest_marker("timeout") is not None or not minutes:
        return
    limit = float(item.config.getini("timeout") or 0)
    needed = 60.0 * minutes * SLOWER_MACHINE
    if needed > limit:
        item.add_marker(pytest.mark.timeout(needed))


@pytest.fixture(scope="module", autouse=True)
def _compiled_code_released_after_each_module():
    """A pytest worker runs many modules' fits in one process. Every XLA executable keeps
    its machine code in memory maps of its own, and a worker that had compiled a few dozen
    fits went past the kernel's limit on maps per process (vm.max_map_count, 65530): the next
    compilation died with a segmentation fault. A module's compiled functions are shared
    within it; after it they are let go (jax.clear_caches releases the maps)."""
    yield
    if "jax" in sys.modules:
        sys.modules["jax"].clear_caches()
        gc.collect()
