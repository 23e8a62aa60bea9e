"""The crash-safe page journal under the campaign file.

A campaign may be killed (SIGKILL, power cut) at any instant and resumed from its
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

import fcntl
import io
import os
import struct
import zlib

from .encoding import CampaignFileError

JOURNAL_SUFFIX = "-journal"

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


