"""Reading a campaign file back: complete points only, a hot journal applied virtually."""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass, field

import h5py
import numpy as np

from .encoding import (_HDF5_SIGNATURE, CampaignFileError, _check_format, _one_line, _py,
                       _read_attrs, _read_history, _read_text)
from .journal import _read_journal, _RolledBackView

@dataclass
class Campaign:
    """A campaign file's content. Points are complete points only, in collection order; each is
    a dict with the point document's scalars plus "seq" (its number in the file), "run",
    "settings", "loop", "extra", "fourier", "history" and "timeseries_fields"/"timeseries_length"
    ("timeseries" too when read with timeseries=True, else use `timeseries(seq)`)."""
    path: str
    format_version: int
    rig: str
    created: str
    metadata: dict
    points: list[dict]
    events: list[dict]
    runs: list[dict]
    incomplete: int = 0                  # point groups without complete=True (ignored)
    hot_journal: bool = False            # a killed commit was rolled back (in memory) to read it
    attrs: dict = field(default_factory=dict)

    @property
    def started(self) -> str | None:
        return self.runs[0].get("started") if self.runs else self.created

    @property
    def ended(self) -> str | None:
        return self.runs[-1].get("ended") if self.runs else None

    def timeseries(self, seq: int) -> dict[str, np.ndarray]:
        return read_timeseries(self.path, seq)


def _signature_at(path: str) -> bool:
    """HDF5's signature at 0, 512, 1024, ... (a user block may precede it)."""
    with open(path, "rb") as fh:
        size = os.fstat(fh.fileno()).st_size
        off = 0
        while off + 8 <= size:
            fh.seek(off)
            if fh.read(8) == _HDF5_SIGNATURE:
                return True
            off = 512 if off == 0 else off * 2
    return False


class _Opened:
    """Context manager: the campaign file opened read-only (a hot journal applied virtually)."""

    def __init__(self, path):
        self.path = os.fspath(path)
        self.hot = False
        self._view = None
        self.file = None

    def __enter__(self) -> h5py.File:
        path = self.path
        if not os.path.exists(path):
            raise CampaignFileError(f"{path}: no such file")
        if os.path.isdir(path):
            raise CampaignFileError(f"{path}: is a directory, not a campaign file")
        try:
            if not _signature_at(path):
                raise CampaignFileError(f"{path}: not a campaign file (not an HDF5 file)")
            journal = _read_journal(path)
            if journal:
                self.hot = True
                self._view = _RolledBackView(path, *journal)
                self.file = h5py.File(self._view, "r")
            else:
                self.file = h5py.File(path, "r", locking=False)
        except CampaignFileError:
            self._close()
            raise
        except OSError as e:
            self._close()
            raise CampaignFileError(f"{path}: not a readable campaign file (damaged HDF5: "
                                    f"{_one_line(e)})") from None
        try:
            _check_format(path, self.file)
        except CampaignFileError:
            self._close()
            raise
        return self.file

    def _close(self):
        if self.file is not None:
            self.file.close()
        if self._view is not None:
            self._view.close()
        self.file = self._view = None

    def __exit__(self, *exc):
        self._close()


def _read_point(g, with_timeseries: bool) -> dict:
    p = _read_attrs(g, skip=("complete",))
    for k, d in g.items():
        if isinstance(d, h5py.Dataset) and k not in ("history", "history_json"):
            p[k] = d[()]
    for name in ("settings", "loop", "extra"):
        p[name] = _read_attrs(g[name]) if name in g else {}
    p["fourier"] = {ch: {what: d[()] for what, d in cg.items()}
                    for ch, cg in g["fourier"].items()} if "fourier" in g else {}
    p["history"] = _read_history(g)
    ts = g.get("timeseries")
    fields = sorted(ts) if ts is not None else []
    p["timeseries_fields"] = fields
    p["timeseries_length"] = max((ts[k].shape[0] for k in fields if ts[k].ndim), default=0)
    if with_timeseries:
        p["timeseries"] = {k: d[()] for k, d in ts.items()} if ts is not None else {}
    return p


def _read_events(f) -> list[dict]:
    if "events" not in f:
        return []
    out = []
    for row in f["events"][()]:
        ev = {"run": int(row["run"]), "kind": _py(row["kind"]),
              "wall_time": float(row["wall_time"])}
        try:
            ev.update(json.loads(_py(row["doc"])))
        except ValueError:
            ev["text"] = _py(row["text"])
        out.append(ev)
    return out


def _read_runs(f) -> list[dict]:
    runs = []
    for name in sorted(f.get("runs", {})):
        g = f["runs"][name]
        r = _read_attrs(g)
        r["run"] = int(name)
        r["loop"] = _read_attrs(g["loop"]) if "loop" in g else {}
        toml = _read_text(g, "campaign_toml")
        if toml is not None:
            r["campaign_toml"] = toml
        runs.append(r)
    return runs


def _read_once(path: str, with_timeseries: bool) -> Campaign:
    opened = _Opened(path)
    with opened as f:
        meta = f["metadata"]
        metadata = _read_attrs(meta)
        metadata["campaign_toml"] = _read_text(meta, "campaign_toml") or ""
        metadata["campaign"] = json.loads(_read_text(meta, "campaign_json") or "{}")
        metadata["identity"] = _read_attrs(meta["identity"]) if "identity" in meta else {}
        metadata["versions"] = _read_attrs(meta["versions"]) if "versions" in meta else {}
        points, incomplete = [], 0
        for name in sorted(f["points"]):
            g = f["points"][name]
            if not bool(_py(g.attrs.get("complete", False))):
                incomplete += 1
                continue
            points.append(_read_point(g, with_timeseries))
        return Campaign(path=path, format_version=int(_py(f.attrs["format_version"])),
                        rig=_py(f.attrs.get("rig", "unknown")),
                        created=_py(f.attrs.get("created", "")), metadata=metadata,
                        points=points, events=_read_events(f), runs=_read_runs(f),
                        incomplete=incomplete, hot_journal=opened.hot,
                        attrs={k: _py(v) for k, v in f.attrs.items()})


def _retrying(fn, path: str):
    """Run fn(); a campaign being written may change under a reader, so retry a few times."""
    for attempt in range(3):
        try:
            return fn()
        except CampaignFileError:
            raise
        except (OSError, RuntimeError, KeyError, ValueError) as e:
            if attempt == 2:
                raise CampaignFileError(f"{path}: cannot be read ({_one_line(e)})") from None
            time.sleep(0.05 * (attempt + 1))


def read_campaign(path, timeseries: bool = False) -> Campaign:
    """Read a campaign file (complete points only). Raises CampaignFileError for a file that is
    missing, not HDF5, or an HDF5 file that is not a campaign file."""
    path = os.fspath(path)
    return _retrying(lambda: _read_once(path, timeseries), path)


def read_timeseries(path, seq: int) -> dict[str, np.ndarray]:
    """The raw time series of point `seq` (its number in the file)."""
    path = os.fspath(path)

    def once():
        with _Opened(path) as f:
            name = f"{int(seq):06d}"
            g = f["points"].get(name)
            if g is None or not bool(_py(g.attrs.get("complete", False))):
                raise CampaignFileError(f"{path}: no complete point {seq}")
            return {k: d[()] for k, d in g["timeseries"].items()}
    return _retrying(once, path)


def completed_keys(path) -> set[str]:
    """Keys of the complete points in a campaign file (what a resumed campaign may skip)."""
    path = os.fspath(path)

    def once():
        with _Opened(path) as f:
            keys = set()
            for name in f["points"]:
                a = f["points"][name].attrs
                if bool(_py(a.get("complete", False))) and "key" in a:
                    keys.add(str(_py(a["key"])))
            return keys
    return _retrying(once, path)
