"""The campaign file: one HDF5 file per CBC campaign, written document by document.

`CampaignWriter` subscribes to the engine's documents (start, point, fault, link, note, stop)
and appends each one to the file; `read_campaign` and `completed_keys` read it back. The layout
is documented in docs/hdf5_layout.md (root attributes, /metadata, /points/NNNNNN, /events,
/runs); any HDF5 reader can open the files.

Crash safety. A campaign may be killed (SIGKILL, power cut) at any instant and resumed from its
file. Plain HDF5 is not safe for that: it rewrites its own metadata (group indexes, the
superblock) in place, so a process killed while HDF5 writes leaves a file whose group index
points at addresses past its end ("addr overflow"). Measured here with h5py and flush() after
every point, 2 of 119 random kills left such a file; in one the /points index itself was
unreadable, so every point was lost.

So the writer never lets HDF5 touch the committed bytes of the file directly. HDF5 writes through
`_JournaledFile` (h5py's file-object driver), and each document is a transaction, much like
SQLite's rollback journal:

  0. at the first write after a commit, `FILE.h5-journal` is created holding the committed
     length of the file; writes past that length go to disk at once (nothing committed refers
     to them), rewrites of committed bytes are held in memory;
  1. at commit, a new journal that also holds the original contents of every committed byte
     range about to change (with a CRC) is written, fsync'd and renamed over the first;
  2. the held rewrites go to the file, which is truncated to its new length and fsync'd;
  3. the journal is deleted: the commit point.

A kill at any instant before 3 leaves a journal, which the next writer (resume) plays back and
which readers apply virtually, without writing; a torn journal, or one never renamed into place,
means nothing committed was touched. Either way the file reads as exactly the last committed
document sequence: a point is in the file whole, with complete=True, or not at all.
"""

from __future__ import annotations

import atexit
import fcntl
import hashlib
import io
import json
import os
import struct
import threading
import time
import zlib
from dataclasses import dataclass, field
from datetime import datetime, timezone
from typing import Any

import h5py
import numpy as np

__all__ = ["CampaignWriter", "CampaignFileError", "Campaign", "read_campaign", "read_timeseries",
           "completed_keys", "FORMAT_NAME", "FORMAT_VERSION", "FOURIER_ORDER"]

FORMAT_NAME = "cbc-campaign"
FORMAT_VERSION = 1
FOURIER_ORDER = "a0,a1,a2,a3,a4,a5,a6,a7,b1,b2,b3,b4,b5,b6,b7"
RIG_KINDS = {0: "flutter", 1: "oscillator"}
JOURNAL_SUFFIX = "-journal"

_JSON_ATTRS = "_json_attrs"          # attribute listing the attributes stored as JSON text
_POINT_STRUCTURED = ("settings", "loop", "extra", "fourier", "history", "timeseries")
_POINT_RESERVED = ("complete", "seq", "run", _JSON_ATTRS)
_START_STRUCTURED = ("campaign", "campaign_toml", "identity", "versions")
_HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"


class CampaignFileError(Exception):
    """A campaign file that cannot be used. The message is one line and starts with the path."""


def _one_line(text: Any) -> str:
    return " ".join(str(text).split())


# ==== the rollback journal ========================================================================

_PAGE = 4096
_J_MAGIC = b"CBCJRNL1"
_J_END = b"CBCJEND1"
_J_HEAD = struct.Struct("<8sQQ")     # magic, committed size, number of records
_J_REC = struct.Struct("<QQ")        # offset, length (then `length` bytes of original content)
_J_TAIL = struct.Struct("<I8s")      # crc32 of everything before, end magic


def _journal_path(path: str) -> str:
    return os.fspath(path) + JOURNAL_SUFFIX


def _encode_journal(committed: int, records: list[tuple[int, bytes]]) -> bytes:
    parts = [_J_HEAD.pack(_J_MAGIC, committed, len(records))]
    for off, data in records:
        parts += [_J_REC.pack(off, len(data)), data]
    body = b"".join(parts)
    return body + _J_TAIL.pack(zlib.crc32(body), _J_END)


def _decode_journal(blob: bytes) -> tuple[int, list[tuple[int, bytes]]] | None:
    """(committed size, [(offset, original bytes)]), or None for a torn or foreign journal."""
    if len(blob) < _J_HEAD.size + _J_TAIL.size:
        return None
    body, tail = blob[:-_J_TAIL.size], blob[-_J_TAIL.size:]
    crc, end = _J_TAIL.unpack(tail)
    if end != _J_END or zlib.crc32(body) != crc:
        return None
    magic, committed, n = _J_HEAD.unpack_from(body)
    if magic != _J_MAGIC:
        return None
    pos, records = _J_HEAD.size, []
    for _ in range(n):
        off, length = _J_REC.unpack_from(body, pos)
        pos += _J_REC.size
        records.append((off, body[pos:pos + length]))
        pos += length
    return committed, records


def _read_journal(path: str) -> tuple[int, list[tuple[int, bytes]]] | None | bool:
    """The hot journal next to `path`: decoded, None if torn, False if there is none."""
    try:
        with open(_journal_path(path), "rb") as fh:
            return _decode_journal(fh.read())
    except FileNotFoundError:
        return False


def _fsync_dir(path: str) -> None:
    fd = os.open(os.path.dirname(os.path.abspath(path)) or ".", os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _pread_full(fd: int, n: int, off: int) -> bytes:
    """n bytes at off, zero-filled past the end of the file."""
    chunks, got = [], 0
    while got < n:
        b = os.pread(fd, n - got, off + got)
        if not b:
            break
        chunks.append(b)
        got += len(b)
    data = b"".join(chunks)
    return data + bytes(n - len(data)) if len(data) < n else data


def _pwrite_full(fd: int, data, off: int) -> None:
    view = memoryview(data)
    while len(view):
        n = os.pwrite(fd, view, off)
        view, off = view[n:], off + n


def _write_file(path: str, data: bytes, durable: bool) -> None:
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
    try:
        _pwrite_full(fd, data, 0)
        if durable:
            os.fsync(fd)
    finally:
        os.close(fd)


def _remove(path: str) -> None:
    try:
        os.unlink(path)
    except FileNotFoundError:
        pass


def _rollback(path: str, fd: int, durable: bool) -> bool:
    """Play back a hot journal onto the file (the writer holds the lock). True if there was an
    interrupted transaction to undo."""
    _remove(_journal_path(path) + ".tmp")               # never renamed: the file was not touched
    journal = _read_journal(path)
    if journal is False:
        return False
    if journal is not None:
        committed, records = journal
        for off, data in records:
            _pwrite_full(fd, data, off)
        os.ftruncate(fd, committed)
        os.fsync(fd)
    # a torn journal was cut short before the file was touched: nothing to undo
    os.unlink(_journal_path(path))
    if durable:
        _fsync_dir(path)
    return journal is not None


class _JournaledFile(io.RawIOBase):
    """The campaign file as HDF5 sees it through h5py's file-object driver.

    A transaction starts with the first write after a commit: a journal holding only the
    committed length is written (so a kill mid-transaction rolls back to exactly that length).
    Writes at or past `committed` then go straight to disk; writes below it are kept in memory
    pages until `commit()`, which replaces the journal (atomically, by rename) with one that also
    holds the original bytes of every changed range, applies the pages, and deletes the journal.
    Holds an exclusive flock on the file, the lock HDF5 itself uses, so neither a second writer
    nor an h5py writer can open it meanwhile.
    """

    def __init__(self, path: str, *, create: bool, durable: bool = True):
        super().__init__()
        self.path = os.fspath(path)
        self.durable = durable
        self._jpath = _journal_path(self.path)
        flags = os.O_RDWR | ((os.O_CREAT | os.O_EXCL) if create else 0)
        try:
            self._fd = os.open(self.path, flags, 0o644)
        except OSError as e:
            raise CampaignFileError(f"{self.path}: cannot {'create' if create else 'open'} "
                                    f"({e.strerror})") from None
        try:
            fcntl.flock(self._fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(self._fd)
            raise CampaignFileError(f"{self.path}: in use (another process has it open)") from None
        if create:                                        # a stale journal is not this file's
            _remove(self._jpath)
            _remove(self._jpath + ".tmp")
        self.rolled_back = _rollback(self.path, self._fd, durable)
        self._in_txn = False
        self._committed = self._size = os.fstat(self._fd).st_size
        self._low = self._committed          # lowest logical truncation in this transaction
        self._pages: dict[int, bytearray] = {}
        self._pos = 0

    # ---- file-object protocol used by h5py's driver --------------------------------------------
    def readable(self):
        return True

    def writable(self):
        return True

    def seekable(self):
        return True

    def seek(self, offset, whence=io.SEEK_SET):
        if whence == io.SEEK_SET:
            self._pos = offset
        elif whence == io.SEEK_CUR:
            self._pos += offset
        else:
            self._pos = self._size + offset
        return self._pos

    def tell(self):
        return self._pos

    def readinto(self, b):
        out = memoryview(b).cast("B")
        off = self._pos
        n = max(0, min(len(out), self._size - off))
        if n == 0:
            return 0
        end = off + n
        out[:n] = _pread_full(self._fd, n, off)
        lo, hi = max(off, self._low), min(end, self._committed)
        if lo < hi:                                      # logically truncated: zeros
            out[lo - off:hi - off] = bytes(hi - lo)
        if self._pages and off < self._committed:
            for p in range(off // _PAGE, (min(end, self._committed) - 1) // _PAGE + 1):
                page = self._pages.get(p)
                if page is not None:
                    s = max(off, p * _PAGE)
                    e = min(end, (p + 1) * _PAGE, self._committed)
                    out[s - off:e - off] = page[s - p * _PAGE:e - p * _PAGE]
        self._pos = end
        return n

    def write(self, b):
        self._begin()
        data = memoryview(b).cast("B")
        off, n = self._pos, len(data)
        split = min(max(self._committed - off, 0), n)    # bytes that land on committed ones
        if split:
            self._hold(off, data[:split])
        if split < n:
            _pwrite_full(self._fd, data[split:], off + split)
        self._pos = off + n
        self._size = max(self._size, off + n)
        return n

    def truncate(self, size=None):
        size = self._pos if size is None else size
        if size == self._size and size == os.fstat(self._fd).st_size:
            return size                                  # HDF5 does this on every flush
        self._begin()
        if size < self._committed:
            self._low = min(self._low, size)
            for p in [p for p in self._pages if p * _PAGE >= size]:
                del self._pages[p]
            page = self._pages.get(size // _PAGE)
            if page is not None:
                page[size % _PAGE:] = bytes(_PAGE - size % _PAGE)
            os.ftruncate(self._fd, self._committed)      # drop the uncommitted tail only
        else:
            os.ftruncate(self._fd, size)
        self._size = size
        return size

    def flush(self):
        pass                                             # commit() is the only durable step

    # ---- transactions ------------------------------------------------------------------------
    def _hold(self, off: int, data: memoryview) -> None:
        end, pos = off + len(data), off
        while pos < end:
            p = pos // _PAGE
            page = self._pages.get(p)
            if page is None:
                start = p * _PAGE
                page = bytearray(_pread_full(self._fd, _PAGE, start))
                keep = max(0, min(_PAGE, min(self._committed, self._low) - start))
                page[keep:] = bytes(_PAGE - keep)
                self._pages[p] = page
            e = min(end, (p + 1) * _PAGE)
            page[pos - p * _PAGE:e - p * _PAGE] = data[pos - off:e - off]
            pos = e

    def _apply_page(self, offset: int, data) -> None:
        _pwrite_full(self._fd, data, offset)

    def _begin(self) -> None:
        if not self._in_txn:
            _write_file(self._jpath, _encode_journal(self._committed, []), durable=False)
            self._in_txn = True

    def commit(self) -> None:
        """Make everything written since the last commit part of the file, atomically."""
        if not self._in_txn:
            return
        changed = [(p * _PAGE, min((p + 1) * _PAGE, self._committed)) for p in sorted(self._pages)]
        if self._low < self._committed:
            changed.append((self._low, self._committed))
        if changed:
            changed.sort()
            merged = [list(changed[0])]
            for s, e in changed[1:]:
                if s <= merged[-1][1]:
                    merged[-1][1] = max(merged[-1][1], e)
                else:
                    merged.append([s, e])
            records = [(s, _pread_full(self._fd, e - s, s)) for s, e in merged]
            tmp = self._jpath + ".tmp"
            _write_file(tmp, _encode_journal(self._committed, records), self.durable)
            os.replace(tmp, self._jpath)
            if self.durable:
                _fsync_dir(self.path)
            hi = min(self._committed, self._size)
            for s in range(self._low, hi, 1 << 20):      # re-extended after a truncation
                _pwrite_full(self._fd, bytes(min(1 << 20, hi - s)), s)
            for p in sorted(self._pages):
                start = p * _PAGE
                n = min(_PAGE, self._committed - start, self._size - start)
                if n > 0:
                    self._apply_page(start, memoryview(self._pages[p])[:n])
        if os.fstat(self._fd).st_size != self._size:
            os.ftruncate(self._fd, self._size)
        if self.durable:
            os.fsync(self._fd)
        os.unlink(self._jpath)                           # the commit point
        if self.durable:
            _fsync_dir(self.path)
        self._committed = self._low = self._size
        self._pages.clear()
        self._in_txn = False

    def close(self):
        """Release the file; anything not committed is dropped (the file keeps its last commit)."""
        if not self.closed:
            os.close(self._fd)
        super().close()


class _RolledBackView(io.RawIOBase):
    """Read-only view of a file with a hot journal applied virtually (no write, no lock)."""

    def __init__(self, path: str, committed: int, records: list[tuple[int, bytes]]):
        super().__init__()
        self._fd = os.open(path, os.O_RDONLY)
        self._size = committed
        self._records = records
        self._pos = 0

    def readable(self):
        return True

    def seekable(self):
        return True

    def seek(self, offset, whence=io.SEEK_SET):
        base = {io.SEEK_SET: 0, io.SEEK_CUR: self._pos, io.SEEK_END: self._size}[whence]
        self._pos = base + offset
        return self._pos

    def tell(self):
        return self._pos

    def readinto(self, b):
        out = memoryview(b).cast("B")
        off = self._pos
        n = max(0, min(len(out), self._size - off))
        end = off + n
        out[:n] = _pread_full(self._fd, n, off)
        for roff, data in self._records:
            s, e = max(off, roff), min(end, roff + len(data))
            if s < e:
                out[s - off:e - off] = data[s - roff:e - roff]
        self._pos = end
        return n

    def close(self):
        if not self.closed:
            os.close(self._fd)
        super().close()


# ==== attributes: native where HDF5 has a type, JSON text otherwise ===============================

def _native(v):
    if isinstance(v, (bool, np.bool_)):
        return np.bool_(v)
    if isinstance(v, (int, np.integer)):
        return np.int64(v) if -2**63 <= int(v) < 2**63 else None
    if isinstance(v, (float, np.floating)):
        return np.float64(v)
    if isinstance(v, str):
        return v
    if isinstance(v, np.ndarray) and v.dtype.kind in "biuf" and v.ndim == 1 and v.size <= 1024:
        return v
    return None


def _jsonable(v):
    if isinstance(v, dict):
        return {str(k): _jsonable(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_jsonable(x) for x in v]
    if isinstance(v, np.ndarray):
        return _jsonable(v.tolist())
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, bytes):
        return v.decode("utf-8", "replace")
    if v is None or isinstance(v, (bool, int, float, str)):
        return v
    return str(v)


def _dumps(v) -> str:
    return json.dumps(_jsonable(v))


def _py(v):
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, bytes):
        return v.decode("utf-8", "replace")
    return v


def _write_attrs(obj, mapping: dict, skip=()) -> None:
    as_json = set(json.loads(obj.attrs[_JSON_ATTRS])) if _JSON_ATTRS in obj.attrs else set()
    for k, v in mapping.items():
        k = str(k)
        if k in skip:
            continue
        native = _native(v)
        if native is None:
            obj.attrs[k] = _dumps(v)
            as_json.add(k)
        else:
            obj.attrs[k] = native
            as_json.discard(k)
    if as_json:
        obj.attrs[_JSON_ATTRS] = json.dumps(sorted(as_json))


def _read_attrs(obj, skip=()) -> dict:
    as_json = set(json.loads(obj.attrs[_JSON_ATTRS])) if _JSON_ATTRS in obj.attrs else set()
    out = {}
    for k, v in obj.attrs.items():
        if k == _JSON_ATTRS or k in skip:
            continue
        out[k] = json.loads(_py(v)) if k in as_json else _py(v)
    return out


def _write_text(group, name: str, text: str) -> None:
    group.create_dataset(name, data=text, dtype=h5py.string_dtype())


def _read_text(group, name: str) -> str | None:
    return group[name].asstr()[()] if name in group else None


# ==== history tables ==============================================================================

def _column_dtype(values: list):
    if all(isinstance(v, (bool, np.bool_)) for v in values):
        return np.bool_
    if any(isinstance(v, (bool, np.bool_)) for v in values):
        return None
    if all(isinstance(v, (int, np.integer)) for v in values):
        return np.int64
    if all(isinstance(v, (int, float, np.integer, np.floating)) for v in values):
        return np.float64
    if all(isinstance(v, str) for v in values):
        return h5py.string_dtype()
    return None


def _write_history(group, rows: list) -> None:
    """A compound dataset, one field per key, when every row has the same scalar keys; a JSON
    text dataset `history_json` otherwise."""
    rows = list(rows or [])
    keys = list(rows[0].keys()) if rows and isinstance(rows[0], dict) else []
    dtypes = []
    if keys and all(isinstance(r, dict) and list(r.keys()) == keys for r in rows):
        for k in keys:
            dt = _column_dtype([r[k] for r in rows])
            if dt is None:
                break
            dtypes.append((str(k), dt))
    if keys and len(dtypes) == len(keys):
        table = np.empty(len(rows), dtype=np.dtype(dtypes))
        for k, _ in dtypes:
            table[k] = [r[k] for r in rows]
        group.create_dataset("history", data=table)
    else:
        _write_text(group, "history_json", _dumps(rows))


def _read_history(group) -> list[dict]:
    if "history" in group:
        table = group["history"][()]
        names = table.dtype.names
        return [{k: _py(row[k]) for k in names} for row in table]
    if "history_json" in group:
        return json.loads(_read_text(group, "history_json"))
    return []


# ==== the writer ==================================================================================

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


# ==== reading =====================================================================================

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


def _check_format(path: str, f: h5py.File) -> None:
    name = _py(f.attrs.get("format", None))
    if name != FORMAT_NAME:
        raise CampaignFileError(f"{path}: not a campaign file (an HDF5 file without "
                                f"format={FORMAT_NAME!r} in its root attributes)")
    version = int(_py(f.attrs.get("format_version", 0)))
    if version > FORMAT_VERSION:
        raise CampaignFileError(f"{path}: campaign format version {version} is newer than this "
                                f"reader's ({FORMAT_VERSION}); update the package")


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
