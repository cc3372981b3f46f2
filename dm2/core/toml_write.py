"""TOML text from plain values: the writer behind every TOML file dm2 writes (scenarios in
recordings, calibration files, cell files, the configuration beside a report). Reading is
:func:`tomllib.loads` (see :func:`dm2.core.config.read_toml`); what this writes reads back equal.
"""

from __future__ import annotations

import numbers
import re
from typing import Any

import numpy as np


def dump_toml(data: dict[str, Any]) -> str:
    """Write a dict of plain values (str, int, float, bool, lists, tables) as TOML."""
    scalars = {k: v for k, v in data.items() if not isinstance(v, dict) and not _is_table_list(v)}
    tables = {k: v for k, v in data.items() if isinstance(v, dict)}
    table_lists = {k: v for k, v in data.items() if _is_table_list(v)}
    out = [f"{_toml_key(k)} = {_toml_value(v)}" for k, v in scalars.items()]
    for k, v in tables.items():
        out.append("")
        out.extend(_toml_table(_toml_key(k), v))
    for k, rows in table_lists.items():
        for row in rows:
            out.append("")
            out.append(f"[[{_toml_key(k)}]]")
            out.extend(f"{_toml_key(rk)} = {_toml_value(rv)}" for rk, rv in row.items())
    return "\n".join(out) + "\n"


def _is_table_list(v) -> bool:
    return isinstance(v, list) and bool(v) and all(isinstance(x, dict) for x in v)


def _toml_table(name: str, table: dict) -> list[str]:
    lines = [f"[{name}]"]
    nested = []
    for k, v in table.items():
        if isinstance(v, dict):
            nested.append((k, v))
        else:
            lines.append(f"{_toml_key(k)} = {_toml_value(v)}")
    for k, v in nested:
        lines.append("")
        lines.extend(_toml_table(f"{name}.{_toml_key(k)}", v))
    return lines


def _toml_value(v) -> str:
    if isinstance(v, bool | np.bool_):
        return "true" if v else "false"
    if isinstance(v, numbers.Integral):
        return str(int(v))
    if isinstance(v, numbers.Real):  # numpy scalars too (their repr is not TOML)
        return repr(float(v))
    if isinstance(v, str):
        return _toml_string(v)
    if isinstance(v, list | tuple):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{_toml_key(k)} = {_toml_value(x)}" for k, x in v.items()) + " }"
    raise TypeError(f"cannot write {type(v).__name__} to TOML")


_BARE_KEY = re.compile(r"[A-Za-z0-9_-]+")


def _toml_key(k) -> str:
    k = str(k)
    return k if _BARE_KEY.fullmatch(k) else _toml_string(k)


_ESCAPES = {'"': '\\"', "\\": "\\\\", "\b": "\\b", "\t": "\\t", "\n": "\\n", "\f": "\\f",
            "\r": "\\r"}


def _toml_string(s: str) -> str:
    """A TOML basic string: quotes, backslashes and control characters escaped."""
    out = []
    for ch in s:
        if ch in _ESCAPES:
            out.append(_ESCAPES[ch])
        elif ord(ch) < 0x20 or ord(ch) == 0x7F:
            out.append(f"\\u{ord(ch):04x}")
        else:
            out.append(ch)
    return '"' + "".join(out) + '"'
