"""TOML text from plain values: the writer behind every TOML file dm2 writes (scenarios in
recordings, calibration files, cell files, the configuration beside a report), through
``tomlkit``. Reading is :func:`tomllib.loads` (see :func:`dm2.core.config.read_toml`); what this
writes reads back equal.
"""

from __future__ import annotations

import numbers
from typing import Any

import numpy as np
import tomlkit


def dump_toml(data: dict[str, Any]) -> str:
    """Write a dict of plain values (str, int, float, bool, lists, tables, lists of tables;
    numpy scalars and arrays too) as TOML. Keys that are not bare are quoted, strings escaped."""
    return tomlkit.dumps(_plain(data))


def _plain(v):
    """``v`` with numpy scalars and arrays as Python values and tuples as lists."""
    if isinstance(v, dict):
        return {str(k): _plain(x) for k, x in v.items()}
    if isinstance(v, np.ndarray):
        return _plain(v.tolist())
    if isinstance(v, list | tuple):
        return [_plain(x) for x in v]
    if isinstance(v, bool | np.bool_):
        return bool(v)
    if isinstance(v, numbers.Integral):
        return int(v)
    if isinstance(v, numbers.Real):
        return float(v)
    if isinstance(v, str):
        return v
    raise TypeError(f"cannot write {type(v).__name__} to TOML")
