"""What every command writes beside its results: JSON written atomically, and the
provenance of a run (the version, when, the command, and every input with its hash)."""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
import os

from ..model_file import _jsonable, _version


def write_json(path, obj) -> None:
    tmp = os.fspath(path) + ".tmp"
    with open(tmp, "w") as fh:
        json.dump(obj, fh, indent=2, default=_jsonable)
        fh.write("\n")
    os.replace(tmp, path)


def write_text(path, text: str) -> None:
    with open(path, "w") as fh:
        fh.write(text)


def input_records(paths) -> list:
    """Each input's absolute path, and for a file its size and SHA-256."""
    out = []
    for p in paths:
        rec = {"path": os.path.abspath(p)}
        if os.path.isfile(p):
            h = hashlib.sha256()
            with open(p, "rb") as fh:
                for chunk in iter(lambda: fh.read(1 << 20), b""):
                    h.update(chunk)
            rec.update(bytes=os.path.getsize(p), sha256=h.hexdigest())
        out.append(rec)
    return out


def provenance(command: str, paths) -> dict:
    """{"version", "written", "command", "inputs"}: what produced a result, from what."""
    return {"version": _version(),
            "written": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
            "command": command, "inputs": input_records(paths)}
