"""How a campaign's documents sit in HDF5: the format's constants, attributes (native where HDF5
has a type, JSON text otherwise) and history tables. Shared by the writer and the reader."""

from __future__ import annotations

import json
from typing import Any

import h5py
import numpy as np

FORMAT_NAME = "cbc-campaign"
FORMAT_VERSION = 1
FOURIER_ORDER = "a0,a1,a2,a3,a4,a5,a6,a7,b1,b2,b3,b4,b5,b6,b7"
RIG_KINDS = {0: "flutter", 1: "oscillator"}

_JSON_ATTRS = "_json_attrs"          # attribute listing the attributes stored as JSON text
_POINT_STRUCTURED = ("settings", "loop", "extra", "fourier", "history", "timeseries")
_POINT_RESERVED = ("complete", "seq", "run", _JSON_ATTRS)
_START_STRUCTURED = ("campaign", "campaign_toml", "identity", "versions")
_HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"


class CampaignFileError(Exception):
    """A campaign file that cannot be used. The message is one line and starts with the path."""


def _one_line(text: Any) -> str:
    return " ".join(str(text).split())



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


def _check_format(path: str, f: h5py.File) -> None:
    name = _py(f.attrs.get("format", None))
    if name != FORMAT_NAME:
        raise CampaignFileError(f"{path}: not a campaign file (an HDF5 file without "
                                f"format={FORMAT_NAME!r} in its root attributes)")
    version = int(_py(f.attrs.get("format_version", 0)))
    if version > FORMAT_VERSION:
        raise CampaignFileError(f"{path}: campaign format version {version} is newer than this "
                                f"reader's ({FORMAT_VERSION}); update the package")
