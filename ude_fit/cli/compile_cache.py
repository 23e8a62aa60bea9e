"""Compiled code kept between runs: the command line stores JAX's XLA executables on disk,
so a second fit of data of the same shape loads its shooting losses and continuation steps
instead of compiling them again (a one-start aerofoil fit: 57 s cold, 27 s warm on 2
cores; docs/fitting.md). The results are the same either way: an executable is found
again only for the same program, JAX version and machine.

Where: ``$UDE_FIT_COMPILE_CACHE`` (set it empty to turn the cache off), else
``$XDG_CACHE_HOME/ude-fit/xla``, else ``~/.cache/ude-fit/xla``. A directory JAX is already
given (``$JAX_COMPILATION_CACHE_DIR``) is left as it is. The cache holds at most
``MAX_BYTES``, least recently used entries going first; the bound also makes JAX lock
the directory (with the filelock package, a dependency), so runs at the same time
cannot tear an entry. Importing ude_fit does none of this; the command line does, as it
switches on float64.
"""

from __future__ import annotations

import importlib.util
import os
import sys
from pathlib import Path

ENV = "UDE_FIT_COMPILE_CACHE"
MAX_BYTES = 2 << 30


def cache_dir(environ=os.environ) -> Path | None:
    """The directory the command line keeps compiled code in; None where it is off."""
    if ENV in environ:
        return Path(environ[ENV]).expanduser() if environ[ENV] else None
    base = environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "ude-fit" / "xla"


def use_compile_cache(environ=os.environ) -> Path | None:
    """Point JAX's persistent compilation cache at :func:`cache_dir` (every executable,
    however fast it compiled) unless JAX already has one; returns the directory in use.
    A directory that cannot be made costs only speed: one line on stderr says so."""
    import jax
    given = jax.config.jax_compilation_cache_dir
    if given:
        return Path(given)
    where = cache_dir(environ)
    if where is None:
        return None
    if importlib.util.find_spec("filelock") is None:    # JAX locks a bounded cache with it
        return _not_kept(where, "the filelock package is not installed")
    try:
        where.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        return _not_kept(where, f"{exc.strerror or exc}; set {ENV} to another folder")
    mend_entries(where)
    try:
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
        jax.config.update("jax_compilation_cache_max_size", MAX_BYTES)
    except AttributeError as exc:                       # a JAX without these settings
        return _not_kept(where, str(exc))
    jax.config.update("jax_compilation_cache_dir", str(where))
    return where


def mend_entries(where: Path) -> int:
    """Give every entry of the cache at ``where`` that has no access-time record one (its
    file's modification time); returns how many were mended.

    JAX's bounded cache reads every entry's record before it writes a new entry, so a single
    entry without one (a run killed between the entry's two writes, or a process that wrote
    into the folder with no size bound) makes every later write fail, each with a warning
    on stderr, and nothing new is kept (measured: 26 such entries, 10 warnings per fit).
    Done under JAX's own lock on the folder; a folder it cannot mend costs only speed."""
    names = _entry_suffixes()
    if names is None:
        return 0
    entry_suffix, access_suffix = names
    import filelock
    mended = 0
    try:
        # the lock file JAX's LRU cache takes on the folder (jax._src.lru_cache.LRUCache)
        with filelock.FileLock(where / ".lockfile", timeout=10):
            for entry in where.glob(f"*{entry_suffix}"):
                access = entry.with_name(entry.name[:-len(entry_suffix)] + access_suffix)
                if not access.exists():
                    access.write_bytes(entry.stat().st_mtime_ns.to_bytes(8, "little"))
                    mended += 1
    except (OSError, filelock.Timeout) as exc:
        print(f"ude-fit: note: the compiled-code folder {where} could not be checked "
              f"({exc}); some compiled code may not be kept", file=sys.stderr)
    return mended


def _entry_suffixes() -> tuple[str, str] | None:
    """The file suffixes of a cache entry and of its access-time record in JAX's LRU cache;
    None for a JAX that names them otherwise (then nothing is mended)."""
    try:
        from jax._src import lru_cache
        return str(lru_cache._CACHE_SUFFIX), str(lru_cache._ATIME_SUFFIX)
    except (ImportError, AttributeError):
        return None


def _not_kept(where: Path, why: str) -> None:
    print(f"ude-fit: note: compiled code is not kept between runs ({where}: {why})",
          file=sys.stderr)
    return None
