"""`CampaignWriter`: the subscriber that appends the engine's documents to a campaign file, each
one a journaled transaction (see journal.py)."""

from __future__ import annotations

import atexit
import hashlib
import os
import threading
import time
from datetime import datetime, timezone

import h5py
import numpy as np

from .encoding import (_POINT_RESERVED, _POINT_STRUCTURED, _START_STRUCTURED, FORMAT_NAME,
                       FORMAT_VERSION, FOURIER_ORDER, RIG_KINDS, CampaignFileError, _check_format,
                       _dumps, _native, _one_line, _py, _write_attrs, _write_history, _write_text)
from .journal import _journal_path, _JournaledFile
from .reader import completed_keys

def _now_iso() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="seconds")


def _rig_of(doc: dict) -> str:
    kind = (doc.get("identity") or {}).get("rig_kind")
    try:
        if int(kind) in RIG_KINDS:
            return RIG_KINDS[int(kind)]
    except (TypeError, ValueError):
        pass
    campaign = doc.get("campaign") or {}
    for rig in (campaign.get("rig"), (campaign.get("campaign") or {}).get("rig")):
        if isinstance(rig, dict):
            rig = rig.get("kind") or rig.get("type")
        if rig in ("flutter", "oscillator"):
            return rig
    return "unknown"


_EVENT_DTYPE = np.dtype([("run", np.int32), ("kind", h5py.string_dtype()),
                         ("wall_time", np.float64), ("rig_time", np.float64),
                         ("code", np.int64), ("text", h5py.string_dtype()),
                         ("doc", h5py.string_dtype())])


class CampaignWriter:
    """Subscriber that appends the engine's documents to a campaign file.

    CampaignWriter(path) creates the file on the "start" document and refuses to overwrite an
    existing one (unless overwrite=True). CampaignWriter(path, resume=True) continues an existing
    file: it plays back a hot journal, deletes incomplete point groups, leaves metadata and points
    as they are and adds a /runs entry. Every document is committed before the call returns.
    durable=False skips the fsyncs (still safe against a killed process, not a power cut).
    """

    def __init__(self, path, resume: bool = False, *, overwrite: bool = False,
                 durable: bool = True):
        self.path = os.fspath(path)
        self.resume = resume
        self.overwrite = overwrite
        self.durable = durable
        self._fobj: _JournaledFile | None = None
        self._h5: h5py.File | None = None
        self._pending: list[tuple[str, dict]] = []       # documents before "start"
        self._lock = threading.RLock()
        self.run = -1
        self.next_seq = 0
        self.removed_incomplete = 0
        self.recovered_journal = False
        if resume:
            completed_keys(self.path)                    # a clear error now, before the rig moves

    # ---- subscriber --------------------------------------------------------------------------
    def __call__(self, kind: str, doc: dict) -> None:
        with self._lock:
            self._handle(kind, doc)

    def _handle(self, kind: str, doc: dict) -> None:
        if kind == "start":
            self._start(doc)
            for k, d in self._pending:
                self._handle(k, d)
            self._pending.clear()
            return
        if self._h5 is None:
            self._pending.append((kind, doc))
            return
        if kind == "point":
            self._point(doc)
        elif kind == "stop":
            self._stop(doc)
            return
        else:
            self._event(kind, doc)
        self._commit()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def close(self) -> None:
        """Commit and release the file. A run that saw no "stop" is marked as such."""
        with self._lock:
            self._close()

    def _close(self) -> None:
        if self._h5 is None:
            return
        atexit.unregister(self.close)
        runs = self._h5["runs"]
        run = runs[f"{self.run:03d}"]
        if "ended" not in run.attrs:
            run.attrs["ended"] = _now_iso()
            run.attrs["stop_reason"] = "closed without a stop document"
        self._commit()
        self._h5.close()
        self._fobj.commit()                              # whatever closing wrote
        self._fobj.close()
        self._h5 = self._fobj = None

    # ---- documents ---------------------------------------------------------------------------
    def _commit(self) -> None:
        self._h5.flush()
        self._fobj.commit()

    def _start(self, doc: dict) -> None:
        if self._h5 is not None:                          # a second start: a new run, same file
            self._close()
            self.resume = True
        self.removed_incomplete, self.recovered_journal = 0, False
        exists = os.path.exists(self.path)
        if self.resume:
            if not exists:
                raise CampaignFileError(f"{self.path}: cannot resume: no such file")
            self._open_existing(doc)
        else:
            if exists and not self.overwrite:
                raise CampaignFileError(f"{self.path}: already exists (resume it, or choose "
                                        "another file)")
            if exists:
                os.unlink(self.path)
                if os.path.exists(_journal_path(self.path)):
                    os.unlink(_journal_path(self.path))
            self._create(doc)
        atexit.register(self.close)                       # a normal exit without close()
        runs = self._h5.require_group("runs")
        self.run = len(runs)
        run = runs.create_group(f"{self.run:03d}")
        meta = self._h5["metadata"]
        toml = doc.get("campaign_toml") or ""
        sha = hashlib.sha256(toml.encode()).hexdigest()
        _write_attrs(run, {
            "started": doc.get("started") or _now_iso(), "command": list(doc.get("command") or []),
            "seed": doc.get("seed"), "rig_url": doc.get("rig_url", ""),
            "resumed": bool(self.resume), "points_at_start": self.next_seq,
            "campaign_sha256": sha, "identity": doc.get("identity") or {},
            "versions": doc.get("versions") or {},
            "removed_incomplete": self.removed_incomplete,
            "recovered_journal": bool(self.recovered_journal)})
        if self.resume and sha != meta.attrs.get("campaign_sha256"):
            _write_text(run, "campaign_toml", toml)       # the campaign changed on resume
        self._commit()

    def _create(self, doc: dict) -> None:
        self._fobj = _JournaledFile(self.path, create=True, durable=self.durable)
        try:
            self._h5 = h5py.File(self._fobj, "w", libver="earliest")
        except Exception:
            self._fobj.close()
            raise
        f = self._h5
        f.attrs["format"] = FORMAT_NAME
        f.attrs["format_version"] = np.int64(FORMAT_VERSION)
        f.attrs["rig"] = _rig_of(doc)
        f.attrs["created"] = doc.get("started") or _now_iso()
        f.attrs["writer"] = "cbc_controller.log.CampaignWriter"
        f.attrs["fourier_order"] = FOURIER_ORDER
        meta = f.create_group("metadata")
        toml = doc.get("campaign_toml") or ""
        _write_text(meta, "campaign_toml", toml)
        _write_text(meta, "campaign_json", _dumps(doc.get("campaign") or {}))
        _write_attrs(meta, {k: v for k, v in doc.items() if k not in _START_STRUCTURED})
        meta.attrs["campaign_sha256"] = hashlib.sha256(toml.encode()).hexdigest()
        _write_attrs(meta.create_group("identity"), doc.get("identity") or {})
        _write_attrs(meta.create_group("versions"), doc.get("versions") or {})
        f.create_group("points")
        f.create_dataset("events", shape=(0,), maxshape=(None,), chunks=(64,), dtype=_EVENT_DTYPE)
        f.create_group("runs")
        self.next_seq = 0

    def _open_existing(self, doc: dict) -> None:
        self._fobj = _JournaledFile(self.path, create=False, durable=self.durable)
        self.recovered_journal = self._fobj.rolled_back
        try:
            self._h5 = h5py.File(self._fobj, "r+")
        except Exception as e:
            self._fobj.close()
            raise CampaignFileError(f"{self.path}: cannot be opened for resume "
                                    f"({_one_line(e)})") from None
        f = self._h5
        try:
            _check_format(self.path, f)
            rig, new = _py(f.attrs.get("rig", "unknown")), _rig_of(doc)
            if "unknown" not in (rig, new) and rig != new:
                raise CampaignFileError(f"{self.path}: is a {rig} campaign; the rig is a {new}")
        except Exception:
            f.close()
            self._fobj.close()
            raise
        if rig == "unknown" and new != "unknown":
            f.attrs["rig"] = new
        points = f["points"]
        names = sorted(points)
        for name in names:
            if not points[name].attrs.get("complete", False):
                del points[name]
                self.removed_incomplete += 1
        left = [int(n) for n in points]
        self.next_seq = max(left) + 1 if left else 0

    def _point(self, doc: dict) -> None:
        f = self._h5
        name = f"{self.next_seq:06d}"
        g = f["points"].create_group(name)
        try:
            g.attrs["complete"] = False
            _write_point(g, doc, self.next_seq, self.run)
            if _py(f.attrs.get("rig")) == "unknown" and doc.get("rig") in ("flutter", "oscillator"):
                f.attrs["rig"] = doc["rig"]
            g.attrs["complete"] = True                    # last: the point now counts
        except Exception:
            del f["points"][name]
            raise
        self.next_seq += 1

    def _event(self, kind: str, doc: dict) -> None:
        ev = self._h5["events"]
        row = np.zeros(1, dtype=_EVENT_DTYPE)
        wall = doc.get("time") if kind == "link" else None
        if kind == "fault":
            text = str(doc.get("text", ""))
        elif kind == "link":
            text = str(doc.get("event", "")) + (f": {doc['error']}" if doc.get("error") else "")
        elif kind == "note":
            text = str(doc.get("text", ""))
        else:
            text = _dumps(doc)
        code = doc.get("code") if kind == "fault" else None
        row[0] = (self.run, kind, float(wall) if wall is not None else time.time(),
                  float(doc["rig_time"]) if doc.get("rig_time") is not None else np.nan,
                  int(code) if code is not None else -1, text, _dumps(doc))
        n = ev.shape[0]
        ev.resize((n + 1,))
        ev[n] = row[0]

    def _stop(self, doc: dict) -> None:
        run = self._h5["runs"][f"{self.run:03d}"]
        _write_attrs(run, {"ended": doc.get("ended") or _now_iso(),
                           "stop_reason": str(doc.get("reason", "")),
                           "points_at_end": self.next_seq})
        _write_attrs(run.require_group("loop"), doc.get("loop") or {})
        extra = {k: v for k, v in doc.items() if k not in ("ended", "reason", "loop")}
        if extra:
            _write_attrs(run, {"stop_extra": extra})
        self._close()


def _write_point(g, doc: dict, seq: int, run: int) -> None:
    g.attrs["seq"] = np.int64(seq)
    g.attrs["run"] = np.int64(run)
    scalars = {k: v for k, v in doc.items()
               if k not in _POINT_STRUCTURED and k not in _POINT_RESERVED}
    arrays = {k: v for k, v in scalars.items()
              if isinstance(v, np.ndarray) and _native(v) is None}
    _write_attrs(g, {k: v for k, v in scalars.items() if k not in arrays})
    for k, v in arrays.items():
        g.create_dataset(k, data=v)
    for name in ("settings", "loop", "extra"):
        _write_attrs(g.create_group(name), doc.get(name) or {})
    fg = g.create_group("fourier")
    fg.attrs["order"] = FOURIER_ORDER
    for ch, parts in (doc.get("fourier") or {}).items():
        cg = fg.create_group(str(ch))
        for what, arr in parts.items():
            cg.create_dataset(str(what), data=np.asarray(arr, dtype=np.float64))
    _write_history(g, doc.get("history") or [])
    tg = g.create_group("timeseries")
    for fld, arr in (doc.get("timeseries") or {}).items():
        a = np.asarray(arr)
        if a.size and a.ndim >= 1 and a.dtype.kind in "biuf":
            tg.create_dataset(str(fld), data=a, chunks=(min(a.shape[0], 1 << 16), *a.shape[1:]),
                              compression="gzip", compression_opts=1, shuffle=True)
        else:
            tg.create_dataset(str(fld), data=a)

