"""A TOML writer for campaign files: top-level tables of numbers, booleans, strings and
lists of them (all a campaign file holds). Python's tomllib only reads."""

from __future__ import annotations

import json
import math


def _value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if not math.isfinite(v):
            raise ValueError(f"TOML: {v!r} is not a finite number")
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v)          # a TOML basic string: JSON's escapes are TOML's
    if isinstance(v, list):
        return "[" + ", ".join(_value(x) for x in v) + "]"
    raise ValueError(f"TOML: cannot write a {type(v).__name__}")


def dump_toml(doc: dict) -> str:
    """``{"campaign": {"name": "x"}, ...}`` -> TOML text (tables in the given order)."""
    lines = [f"{k} = {_value(v)}" for k, v in doc.items() if not isinstance(v, dict)]
    for name, table in doc.items():
        if isinstance(table, dict):
            lines += ["", f"[{name}]"]
            for k, v in table.items():
                if isinstance(v, dict):
                    raise ValueError(f"TOML: nested table {name}.{k} is not supported")
                lines.append(f"{k} = {_value(v)}")
    return "\n".join(lines).lstrip("\n") + "\n"
