"""One dataset from any mix of campaign files, lee2020 files and folders of them; the
kind of each file decided by its content."""

from __future__ import annotations

import os
from collections.abc import Iterable

from .campaign import _signature_offset, load_campaign
from .lee import _MAT5_HEADER, load_lee
from .stability import StabilityLabels
from .orbit import COORDINATES, DataError, OrbitDataset, _check_file, _one_line


_MAT73_HEADER = b"MATLAB 7.3 MAT-file"


CAMPAIGN_SUFFIXES = (".h5", ".hdf5")


def _folder(path: str) -> list[OrbitDataset]:
    """A folder's datasets: each campaign file in it (.h5, .hdf5), and its lee2020 .mat
    files as one wind-tunnel dataset."""
    names = sorted(n for n in os.listdir(path) if os.path.isfile(os.path.join(path, n)))
    campaigns = [os.path.join(path, n) for n in names if n.lower().endswith(CAMPAIGN_SUFFIXES)]
    has_mat = any(n.lower().endswith(".mat") for n in names)
    if not campaigns and not has_mat:
        raise DataError(f"{path}: a folder with neither campaign files (.h5, .hdf5) nor "
                        "lee2020 .mat files")
    return [load_campaign(p) for p in campaigns] + ([load_lee(path)] if has_mat else [])


def _kind(path: str) -> str:
    """'folder', 'campaign', 'lee' or raises: a file's kind is decided by its content,
    not by its name."""
    _check_file(path, allow_dir=True)
    if os.path.isdir(path):
        return "folder"
    try:
        with open(path, "rb") as fh:
            head = fh.read(128)
        off = _signature_offset(path)
    except OSError as e:
        raise DataError(f"{path}: cannot be read ({_one_line(e)})") from None
    if head.startswith(_MAT73_HEADER):
        raise DataError(f"{path}: a MATLAB v7.3 file; lee2020 files are MATLAB v5 (save with "
                        "-v7)")
    if off is not None:
        return "campaign"
    if head.startswith(_MAT5_HEADER):
        return "lee"
    raise DataError(f"{path}: neither a campaign HDF5 file nor a lee2020 .mat file")


def load(paths, system: str | None = None,
         stability: StabilityLabels | None = None) -> OrbitDataset:
    """One dataset from campaign files, lee2020 .mat files and directories of them.

    All inputs must be of one system (and of `system`, when given); the dataset must not
    be empty. ``stability``: the user's explicit labels, which win over the file names and
    campaign attributes. Every problem is a DataError with a one-line message naming the
    file (or the --stability rule).
    """
    if isinstance(paths, (str, os.PathLike)):
        paths = [paths]
    paths = [os.fspath(p) for p in paths] if isinstance(paths, Iterable) else []
    if not paths:
        raise DataError("no input files given")
    if system is not None and system not in COORDINATES:
        raise DataError(f"unknown system {system!r} (flutter or oscillator)")
    parts = []
    for p in paths:
        kind = _kind(p)
        found = (_folder(p) if kind == "folder" else
                 [load_campaign(p) if kind == "campaign" else load_lee(p)])
        for ds in found:
            _check_system(ds, p, system, parts)
            parts.append(ds)
    orbits = tuple(o for ds in parts for o in ds.orbits)
    if not orbits:
        raise DataError(f"{', '.join(paths)}: no complete points (no point with complete=True "
                        "and status 'ok')")
    ds = OrbitDataset(parts[0].system, orbits, tuple(s for ds in parts for s in ds.sources))
    return ds if stability is None else stability.apply(ds)



def _check_system(ds: OrbitDataset, path: str, system: str | None, parts: list) -> None:
    if system is not None and ds.system != system:
        raise DataError(f"{path}: holds {ds.system} data, but {system} was asked for")
    if parts and ds.system != parts[0].system:
        raise DataError(f"{path}: holds {ds.system} data, but {parts[0].sources[0]} holds "
                        f"{parts[0].system} data; load one system at a time")
