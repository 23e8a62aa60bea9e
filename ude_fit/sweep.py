"""Fit sweeps on Ray: datasets x fit options x seeds, each fit a Ray task running
``ude-fit fit`` in a scratch folder of its node, its output folder sent back to the driver.

A sweep file (TOML; paths relative to it)::

    [sweep]
    name = "widths"               # optional (default: the file's stem)
    system = "oscillator"         # or "flutter"
    datasets = ["osc.h5"]         # data files: each travels to the nodes as bytes
    seeds = [0, 1]
    cpus_per_fit = 1              # Ray CPUs per fit (JAX uses what the node gives it)
    retries = 2                   # Ray task retries when a worker or node dies

    [[options]]                   # one point on the options axis: `ude-fit fit` options,
    label = "narrow"              # spelled as in the command line with "_" for "-"
    width = 8
    starts = 1

The driver writes ``fits/<id>/`` (the fit's own folder: metrics.json, report.md, models,
figures) and one summary table, ``summary.json`` and ``summary.md`` (adequate starts, branch
error, Hopf, fold, time), rewritten after every fit, one record per fit. A rerun skips the
fits that are done. Ray's option-search library (Tune) is not used: the grid is given in
full, and plain tasks return each fit's folder to the driver without shared storage.
"""

from __future__ import annotations

import ctypes
import json
import math
import os
import re
import signal
import subprocess
import sys
import tempfile
import time
import tomllib
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path

SUMMARY_JSON = "summary.json"
SUMMARY_MD = "summary.md"
_LABEL = re.compile(r"^[A-Za-z0-9_.-]+$")
_SYSTEMS = ("flutter", "oscillator")


class SweepError(ValueError):
    """A malformed sweep file (one line, naming the field)."""


# ------------------------------------------------------------------ fit options ---------
@dataclass(frozen=True)
class _Option:
    """A `ude-fit fit` option a sweep may vary; `check` returns the value or raises."""

    def check(self, where: str, value):
        raise NotImplementedError


@dataclass(frozen=True)
class _Choice(_Option):
    choices: tuple[str, ...]

    def check(self, where, value):
        if value not in self.choices:
            raise SweepError(f"{where} = {value!r}: must be one of "
                             + ", ".join(f'"{c}"' for c in self.choices))
        return value


@dataclass(frozen=True)
class _Count(_Option):
    def check(self, where, value):
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise SweepError(f"{where} = {value!r}: expected a positive integer")
        return value


@dataclass(frozen=True)
class _Real(_Option):
    low: float = -math.inf                # value must exceed (strict) or reach it
    strict: bool = False

    def check(self, where, value):
        if isinstance(value, bool) or not isinstance(value, (int, float)) \
                or not math.isfinite(value):
            raise SweepError(f"{where} = {value!r}: expected a finite number")
        if value < self.low or (self.strict and value == self.low):
            raise SweepError(f"{where} = {value!r}: must be {'>' if self.strict else '>='} "
                             f"{self.low:g}")
        return float(value)


_WEIGHT = _Real(0.0)
FIT_OPTIONS: dict[str, _Option] = {
    "approximator": _Choice(("nn", "gp")), "training": _Choice(("trajectory", "periodic")),
    "mechanistic": _Choice(("equation", "periodic")), "starts": _Count(), "width": _Count(),
    "depth": _Count(), "weight_decay": _WEIGHT, "equilibrium_penalty": _WEIGHT,
    "smoothness_penalty": _WEIGHT, "rest_stability": _WEIGHT, "energy_shape": _WEIGHT,
    "energy_rising": _WEIGHT, "param_scale": _Real(0.0, strict=True),
    "param_dependence": _Choice(("input", "polynomial")), "param_degree": _Count(),
    "reference_hopf": _Real(), "reference_fold": _Real(),
}


# ------------------------------------------------------------------ the sweep file ------
@dataclass(frozen=True)
class FitSpec:
    """One fit of the sweep: what a task needs to run it anywhere (no shared files)."""
    id: str
    dataset: str                                  # the file's name on the driver
    system: str
    label: str
    options: tuple[tuple[str, object], ...]
    seed: int
    data: bytes = field(repr=False, default=b"")

    def args(self, data_path: str, out: str) -> list[str]:
        opts = [a for k, v in self.options if k != "label"
                for a in (f"--{k.replace('_', '-')}", str(v))]
        return ["fit", data_path, "--system", self.system, "--seed", str(self.seed), *opts,
                "--out", out, "--quiet"]

    def record(self) -> dict:
        return {"fit": self.id, "dataset": self.dataset, "label": self.label,
                "options": dict(self.options), "seed": self.seed}


@dataclass(frozen=True)
class SweepOptions:
    path: str
    name: str
    text: str
    system: str
    datasets: tuple[str, ...]
    options: tuple[tuple[str, tuple[tuple[str, object], ...]], ...]   # (label, options)
    seeds: tuple[int, ...]
    cpus_per_fit: float = 1.0
    retries: int = 2

    def __post_init__(self):
        where = self.path
        if self.system not in _SYSTEMS:
            raise SweepError(f"{where}: sweep.system = {self.system!r}: must be \"flutter\" "
                             "or \"oscillator\"")
        for axis in ("datasets", "options", "seeds"):
            if not getattr(self, axis):
                raise SweepError(f"{where}: sweep.{axis}: empty grid")
        if not self.cpus_per_fit > 0:
            raise SweepError(f"{where}: sweep.cpus_per_fit must be > 0")
        if self.retries < 0:
            raise SweepError(f"{where}: sweep.retries must be >= 0")

    def fits(self) -> list[FitSpec]:
        out = []
        for data in self.datasets:
            blob = Path(data).read_bytes()
            for label, opts in self.options:
                for seed in self.seeds:
                    out.append(FitSpec(f"{Path(data).stem}-{label}-s{seed}", Path(data).name,
                                       self.system, label, opts, seed, blob))
        return out


def _int(where: str, value) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise SweepError(f"{where} = {value!r}: expected an integer")
    return value


def _options(name: str, i: int, raw) -> tuple[str, tuple]:
    where = f"{name}: options[{i}]"
    if not isinstance(raw, dict):
        raise SweepError(f"{where}: must be a table ([[options]])")
    label = raw.get("label", f"options{i}")
    if not isinstance(label, str) or not _LABEL.match(label):
        raise SweepError(f"{where}.label = {label!r}: letters, digits, '_', '.', '-' only")
    opts = []
    for k, v in raw.items():
        if k == "label":
            continue
        if k not in FIT_OPTIONS:
            raise SweepError(f"{where}.{k}: unknown fit option (known: "
                             f"{', '.join(sorted(FIT_OPTIONS))})")
        opts.append((k, FIT_OPTIONS[k].check(f"{where}.{k}", v)))
    return label, tuple(opts)


def parse_sweep(raw: dict, path: str, text: str = "") -> SweepOptions:
    """The sweep options from a parsed sweep file (paths relative to the file)."""
    name, base = Path(path).name, Path(path).resolve().parent
    for k in raw:
        if k not in ("sweep", "options"):
            raise SweepError(f"{name}: [{k}]: unknown section (known: sweep, options)")
    sweep = raw.get("sweep")
    if not isinstance(sweep, dict):
        raise SweepError(f"{name}: [sweep] is missing")
    known = ("name", "system", "datasets", "seeds", "cpus_per_fit", "retries")
    for k in sweep:
        if k not in known:
            raise SweepError(f"{name}: sweep.{k}: unknown field (known: {', '.join(known)})")
    datasets = sweep.get("datasets")
    if not isinstance(datasets, list) or not all(isinstance(d, str) for d in datasets):
        raise SweepError(f"{name}: sweep.datasets: expected a list of data files")
    files = []
    for i, d in enumerate(datasets):
        p = (base / d).resolve()
        if not p.is_file():
            raise SweepError(f"{name}: sweep.datasets[{i}]: not a file: {p}")
        files.append(str(p))
    if len({Path(f).stem for f in files}) != len(files):
        raise SweepError(f"{name}: sweep.datasets: two data files with the same name")
    seeds = sweep.get("seeds", [0])
    if not isinstance(seeds, list):
        raise SweepError(f"{name}: sweep.seeds: expected a list of integers")
    seeds = tuple(_int(f"{name}: sweep.seeds[{i}]", s) for i, s in enumerate(seeds))
    if len(set(seeds)) != len(seeds):
        raise SweepError(f"{name}: sweep.seeds: a seed given twice")
    options_raw = raw.get("options", [{"label": "default"}])
    if not isinstance(options_raw, list):
        raise SweepError(f"{name}: options: expected [[options]] tables")
    options = tuple(_options(name, i, o) for i, o in enumerate(options_raw))
    if len({label for label, _ in options}) != len(options):
        raise SweepError(f"{name}: options: a label given twice")
    cpus = sweep.get("cpus_per_fit", 1.0)
    if isinstance(cpus, bool) or not isinstance(cpus, (int, float)):
        raise SweepError(f"{name}: sweep.cpus_per_fit = {cpus!r}: expected a number")
    sweep_name = sweep.get("name", Path(path).stem)
    if not isinstance(sweep_name, str):
        raise SweepError(f"{name}: sweep.name = {sweep_name!r}: expected a string")
    return SweepOptions(name, sweep_name, text, str(sweep.get("system")), tuple(files), options,
                        seeds, float(cpus), _int(f"{name}: sweep.retries", sweep.get("retries", 2)))


def load_sweep(path: str | Path) -> SweepOptions:
    """Read and check a sweep file; raises SweepError (one line) on any mistake."""
    path = Path(path)
    try:
        text = path.read_text()
        raw = tomllib.loads(text)
    except OSError as exc:
        raise SweepError(f"{path}: cannot read ({exc.strerror})") from None
    except tomllib.TOMLDecodeError as exc:
        raise SweepError(f"{path.name}: not valid TOML ({exc})") from None
    return parse_sweep(raw, str(path), text)


# ------------------------------------------------------------------ one fit -------------
def _die_with_parent() -> None:
    """Linux: the fit gets SIGTERM when the worker running it dies (a lost node)."""
    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)   # PR_SET_PDEATHSIG
    except OSError:
        pass


def fit_summary(metrics: dict) -> dict:
    """The summary table's numbers from a fit's metrics.json."""
    ude, mech, starts = metrics.get("ude") or {}, metrics.get("mechanistic") or {}, \
        metrics.get("starts") or {}
    return {"adequate": starts.get("adequate"), "starts": starts.get("requested"),
            "branch_rms_mechanistic": mech.get("branch_rms"), "branch_rms_ude": ude.get("branch_rms"),
            "hopf": (ude.get("hopf") or {}).get("model"), "fold": (ude.get("fold") or {}).get("model"),
            "folds": ude.get("folds"), "fit_seconds": metrics.get("seconds")}


def run_fit(spec: FitSpec) -> dict:
    """Run one fit as `ude-fit fit` in a scratch folder; returns its record and its output
    folder's files ({"files": {name: bytes}})."""
    import platform
    with tempfile.TemporaryDirectory(prefix=f"sweep-{spec.id}-") as tmp:
        data = Path(tmp) / spec.dataset
        data.write_bytes(spec.data)
        out = Path(tmp) / "fit"
        t0 = time.monotonic()
        r = subprocess.run([sys.executable, "-m", "ude_fit.cli", *spec.args(str(data), str(out))],
                           cwd=tmp, capture_output=True, text=True, preexec_fn=_die_with_parent)
        wall = round(time.monotonic() - t0, 3)
        files = {f.name: f.read_bytes() for f in sorted(out.glob("*")) if f.is_file()} \
            if out.is_dir() else {}
        rec = {**spec.record(), "wall_s": wall, "node": platform.node()}
        if r.returncode == 0 and "metrics.json" in files:
            return {**rec, "status": "completed", "error": None,
                    **fit_summary(json.loads(files["metrics.json"])), "files": files}
        lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
        return {**rec, "status": "failed", "error": lines[-1] if lines else f"exit {r.returncode}",
                "files": files}


# ------------------------------------------------------------------ the driver ----------
def _connect(address: str | None) -> None:
    try:
        import ray
    except ImportError:
        raise SweepError("Ray is not installed: pip install -e \".[cluster]\"") from None
    if ray.is_initialized():
        return
    where = address or os.environ.get("RAY_ADDRESS")
    try:
        if where:
            ray.init(address=address, log_to_driver=False)
        else:
            ray.init(include_dashboard=False, log_to_driver=False)
    except (ConnectionError, RuntimeError, ValueError) as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise SweepError(f"cannot {'join the Ray cluster at ' + where if where else 'start Ray'}"
                         f": {first}") from None


def _fit_task(spec: FitSpec) -> dict:
    import ray
    rec = run_fit(spec)
    rec["node"] = f"{ray.util.get_node_ip_address()}/{ray.get_runtime_context().get_node_id()[:8]}"
    return rec


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version
    try:
        return version("virtual-cbc-lab")
    except PackageNotFoundError:
        return "unknown"


def _fmt(x, fmt: str) -> str:
    return "-" if x is None else format(x, fmt)


def summary_table(name: str, records: list[dict]) -> str:
    rows = [f"# Sweep {name}\n", "| fit | dataset | options | seed | status | adequate starts "
            "| branch error (mech. / UDE) | Hopf | fold | time (s) | error |",
            "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in records:
        opts = ", ".join(f"{k}={v}" for k, v in r["options"].items()) or "-"
        adequate = "-" if r.get("adequate") is None else f"{r['adequate']}/{r['starts']}"
        err = (f"{_fmt(r.get('branch_rms_mechanistic'), '.3%')} / "
               f"{_fmt(r.get('branch_rms_ude'), '.3%')}")
        rows.append(f"| {r['fit']} | {r['dataset']} | {opts} | {r['seed']} | {r['status']} "
                    f"| {adequate} | {err} | {_fmt(r.get('hopf'), '.4f')} "
                    f"| {_fmt(r.get('fold'), '.4f')} | {_fmt(r.get('wall_s'), '.0f')} "
                    f"| {(r.get('error') or '').replace('|', '/')} |")
    return "\n".join(rows) + "\n"


def run_sweep(options: SweepOptions, out: str | Path, address: str | None = None,
              stream=sys.stderr) -> int:
    """Run every fit not yet done; returns the exit status (0: all completed, 1: some
    failed, 130: interrupted)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    fits = options.fits()
    old = {}
    if (out / SUMMARY_JSON).exists():
        old = {r["fit"]: r for r in json.loads((out / SUMMARY_JSON).read_text())["fits"]}
    records = {f.id: old.get(f.id) or {**f.record(), "status": "pending"} for f in fits}

    def write() -> None:
        doc = {"sweep": options.name, "sweep_file": options.path, "sweep_toml": options.text,
               "system": options.system, "version": _version(),
               "written": datetime.now(timezone.utc).isoformat(),
               "fits": list(records.values())}
        for name, text in ((SUMMARY_JSON, json.dumps(doc, indent=1)),
                           (SUMMARY_MD, summary_table(options.name, list(records.values())))):
            (out / (name + ".tmp")).write_text(text)
            os.replace(out / (name + ".tmp"), out / name)

    todo = [f for f in fits if records[f.id]["status"] not in ("completed", "failed")]
    stream.write(f"sweep {options.name}: {len(fits)} fits, {len(fits) - len(todo)} done, "
                 f"{len(todo)} to run\n")
    write()
    if todo:
        _connect(address)
        import ray
        task = ray.remote(num_cpus=options.cpus_per_fit, max_retries=options.retries,
                          scheduling_strategy="SPREAD")(_fit_task)
        pending = {task.remote(f): f for f in todo}
        t0, done = time.time(), 0
        try:
            while pending:
                ready, _ = ray.wait(list(pending), num_returns=1, timeout=1.0)
                for ref in ready:
                    spec = pending.pop(ref)
                    try:
                        rec = ray.get(ref)
                    except ray.exceptions.RayError as exc:
                        rec = {**spec.record(), "status": "lost",
                               "error": f"{type(exc).__name__}: {str(exc).splitlines()[0]}"}
                    folder = out / "fits" / spec.id
                    folder.mkdir(parents=True, exist_ok=True)
                    for fname, blob in rec.pop("files", {}).items():
                        (folder / fname).write_bytes(blob)
                    records[spec.id] = {**rec, "folder": f"fits/{spec.id}"}
                    write()
                    done += 1
                    el = time.time() - t0
                    stream.write(f"[{done}/{len(todo)}] {spec.id}: {rec['status']}, adequate "
                                 f"{rec.get('adequate', '-')}/{rec.get('starts', '-')}, UDE "
                                 f"branch error {_fmt(rec.get('branch_rms_ude'), '.3%')}, "
                                 f"{_fmt(rec.get('wall_s'), '.0f')} s on {rec.get('node')}"
                                 + (f": {rec['error']}" if rec.get("error") else "")
                                 + f" | elapsed {el:.0f} s, ETA "
                                 f"{el / done * (len(todo) - done):.0f} s\n")
                    stream.flush()
        except KeyboardInterrupt:
            for ref in pending:
                ray.cancel(ref, force=True)
            write()
            stream.write("sweep interrupted: a rerun runs the fits not done\n")
            return 130
    stream.write(f"sweep done; summary: {out / SUMMARY_MD}\n")
    return 0 if all(r["status"] == "completed" for r in records.values()) else 1


# ------------------------------------------------------------------ command -------------
