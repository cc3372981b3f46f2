"""The ``[process]`` and ``[monitor]`` tables of a configuration file, applied over a run's own.

``dm2 monitor --config FILE`` and ``dm2 fit-efficiency --config FILE`` take them from a scenario
file, a cell file (:mod:`dm2.live.config`) or the table ``dm2 fit-efficiency`` writes: a
recording made by the cell itself carries no scenario, and one made by the twin carries the
scenario it was simulated with, which a user may want to monitor with other settings (the cell's
fitted efficiency curve, another voxel size). The file's keys replace the run's, table by table
(a nested table such as ``[monitor.uncertainty]`` key by key); every other table in the file is
ignored. Errors are :class:`~dm2.core.config.ConfigError` naming the file and the field.
"""

from __future__ import annotations

from pathlib import Path

from pydantic import BaseModel, ConfigDict, ValidationError

from dm2.core.config import (
    ConfigError,
    MonitorConfig,
    ProcessConfig,
    format_validation_error,
    read_toml,
)

TABLES = ("process", "monitor")


class _Tables(BaseModel):
    """The two tables (a scenario or cell file's others are ignored)."""

    model_config = ConfigDict(extra="ignore")
    process: ProcessConfig
    monitor: MonitorConfig


def _merged(base: dict, update: dict) -> dict:
    out = dict(base)
    for k, v in update.items():
        out[k] = _merged(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def apply_config_file(path: str | Path, process: ProcessConfig, monitor: MonitorConfig
                      ) -> tuple[ProcessConfig, MonitorConfig]:
    """``process`` and ``monitor`` with the ``[process]`` / ``[monitor]`` tables of the TOML
    file ``path`` applied (see the module docstring).

    Raises
    ------
    ConfigError : the file cannot be read, holds neither table, or a value is invalid
    """
    data = read_toml(path, "configuration")
    if not any(name in data for name in TABLES):
        tables = sorted(k for k, v in data.items() if isinstance(v, dict))
        raise ConfigError(f"{path}: holds no [process] or [monitor] table (its tables: "
                          f"{', '.join(tables) or 'none'})")
    for name in TABLES:
        if name in data and not isinstance(data[name], dict):
            raise ConfigError(f"{path}: '{name}' must be a table, got {data[name]!r}")
    tables = {"process": _merged(process.model_dump(exclude_none=True),
                                 data.get("process", {})),
              "monitor": _merged(monitor.model_dump(exclude_none=True),
                                 data.get("monitor", {}))}
    try:
        out = _Tables.model_validate(tables)
    except ValidationError as exc:
        raise ConfigError(format_validation_error(str(path), exc, _Tables)) from None
    return out.process, out.monitor
