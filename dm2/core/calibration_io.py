"""Calibration files: a :class:`~dm2.core.messages.Calibration` as a small, documented TOML file.

Format (``schema = 1``), every pose a table with a translation in millimetres and a rotation
as a unit quaternion in ABB order ``(qw, qx, qy, qz)``::

    schema = 1

    [T_B_N]                 # nozzle exit in the robot base
    translation_mm = [1300.0, 0.0, 900.0]
    quaternion_wxyz = [0.0, 1.0, 0.0, 0.0]

    [T_F_O]                 # work object (plate corner) on the flange
    translation_mm = [-60.0, -60.0, 150.0]
    quaternion_wxyz = [1.0, 0.0, 0.0, 0.0]

    [sensors.S1]            # each profiler in the robot base (S1, S2, S3)
    translation_mm = [...]
    quaternion_wxyz = [...]

    [provenance]            # optional: where each transform came from (free text)
    T_B_N = "taken from the cell file"
    T_F_O = "estimated: sphere artifact (work object), 24 poses"
    S1 = "estimated: sphere artifact hand-eye solve"

A provenance entry starts with ``estimated`` or ``taken`` (see :data:`PROVENANCE_KINDS`).

Floats are written with ``repr`` so a file read back holds the same numbers bit for bit;
translations survive exactly, rotations to float64 rounding (quaternion <-> matrix).
Bad files raise :class:`~dm2.core.config.ConfigError` naming the file and the field.
"""

from __future__ import annotations

import math
import tomllib
from pathlib import Path

import numpy as np

from dm2.core.config import ConfigError
from dm2.core.frames import from_quat_abb, to_quat_abb
from dm2.core.messages import SENSOR_IDS, Calibration, MessageError
from dm2.core.tolerances import UNIT_NORM_TOL
from dm2.core.toml_write import dump_toml

CALIBRATION_SCHEMA = 1
_POSE_KEYS = ("translation_mm", "quaternion_wxyz")
_UNIT_TOLERANCE = UNIT_NORM_TOL


def _pose_table(T: np.ndarray) -> dict:
    t, q = to_quat_abb(T)
    return {"translation_mm": [float(x) for x in t], "quaternion_wxyz": [float(x) for x in q]}


PROVENANCE_KINDS = ("estimated", "taken")


def _provenance_keys(cal_sensors) -> tuple[str, ...]:
    return ("T_B_N", "T_F_O", *[sid for sid in SENSOR_IDS if sid in cal_sensors])


def calibration_to_toml(cal: Calibration, provenance: dict[str, str] | None = None) -> str:
    """The calibration as TOML text (see the module docstring for the format).

    ``provenance`` maps ``T_B_N``, ``T_F_O`` and sensor ids to a text starting with
    ``estimated`` or ``taken``; when given it must cover every transform of ``cal``.
    """
    data = {
        "schema": CALIBRATION_SCHEMA,
        "T_B_N": _pose_table(cal.T_B_N),
        "T_F_O": _pose_table(cal.T_F_O),
        "sensors": {sid: _pose_table(cal.T_B_S[sid]) for sid in SENSOR_IDS if sid in cal.T_B_S},
    }
    if provenance is not None:
        _check_provenance("<provenance>", provenance, _provenance_keys(cal.T_B_S))
        data["provenance"] = {k: provenance[k] for k in _provenance_keys(cal.T_B_S)}
    header = "# dm2 calibration: translations [mm], quaternions (qw, qx, qy, qz)\n"
    return header + dump_toml(data)


def _check_provenance(source: str, table, keys: tuple[str, ...]) -> dict[str, str]:
    if not isinstance(table, dict):
        raise ConfigError(f"{source}: field 'provenance': expected a table of texts")
    for key, text in table.items():
        if key not in keys:
            raise ConfigError(f"{source}: field 'provenance.{key}': no such transform "
                              f"(expected {', '.join(keys)})")
        if not isinstance(text, str) or not text.startswith(PROVENANCE_KINDS):
            raise ConfigError(f"{source}: field 'provenance.{key}': {text!r} does not start "
                              f"with one of {', '.join(PROVENANCE_KINDS)}")
    missing = [k for k in keys if k not in table]
    if missing:
        raise ConfigError(f"{source}: field 'provenance': missing {', '.join(missing)}")
    return dict(table)


def write_calibration_toml(cal: Calibration, path: str | Path,
                           provenance: dict[str, str] | None = None) -> None:
    """Write ``cal`` to ``path`` as TOML (written to a temporary file, then renamed)."""
    path = Path(path)
    tmp = path.with_name(path.name + ".part")
    tmp.write_text(calibration_to_toml(cal, provenance), encoding="utf-8")
    tmp.replace(path)


def _numbers(source: str, field: str, value, n: int) -> np.ndarray:
    if not isinstance(value, list) or len(value) != n:
        raise ConfigError(f"{source}: field '{field}': expected a list of {n} numbers, "
                          f"got {value!r}")
    out = []
    for v in value:
        if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
            raise ConfigError(f"{source}: field '{field}': {v!r} is not a finite number")
        out.append(float(v))
    return np.asarray(out)


def _pose(source: str, field: str, table) -> np.ndarray:
    if not isinstance(table, dict):
        raise ConfigError(f"{source}: field '{field}': expected a table with "
                          f"{' and '.join(_POSE_KEYS)}")
    for key in table:
        if key not in _POSE_KEYS:
            raise ConfigError(f"{source}: field '{field}.{key}': unknown key")
    for key in _POSE_KEYS:
        if key not in table:
            raise ConfigError(f"{source}: field '{field}.{key}': missing")
    t = _numbers(source, f"{field}.translation_mm", table["translation_mm"], 3)
    q = _numbers(source, f"{field}.quaternion_wxyz", table["quaternion_wxyz"], 4)
    norm = float(np.linalg.norm(q))
    if abs(norm - 1.0) > _UNIT_TOLERANCE:
        raise ConfigError(f"{source}: field '{field}.quaternion_wxyz': not a unit quaternion "
                          f"(norm {norm:.9g})")
    return from_quat_abb(t, q)


def calibration_from_toml(text: str, source: str = "<calibration>") -> Calibration:
    """Parse calibration TOML text; ``source`` names it in errors."""
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{source}: not valid TOML: {exc}") from None
    for key in data:
        if key not in ("schema", "T_B_N", "T_F_O", "sensors", "provenance"):
            raise ConfigError(f"{source}: field '{key}': unknown key")
    schema = data.get("schema")
    if schema != CALIBRATION_SCHEMA:
        raise ConfigError(f"{source}: field 'schema': expected {CALIBRATION_SCHEMA}, "
                          f"got {schema!r}")
    for key in ("T_B_N", "T_F_O", "sensors"):
        if key not in data:
            raise ConfigError(f"{source}: field '{key}': missing")
    sensors = data["sensors"]
    if not isinstance(sensors, dict) or not sensors:
        raise ConfigError(f"{source}: field 'sensors': expected tables [sensors.S1] ...")
    T_B_S = {}
    for sid, table in sensors.items():
        if sid not in SENSOR_IDS:
            raise ConfigError(f"{source}: field 'sensors.{sid}': unknown sensor id "
                              f"(expected one of {', '.join(SENSOR_IDS)})")
        T_B_S[sid] = _pose(source, f"sensors.{sid}", table)
    if "provenance" in data:
        _check_provenance(source, data["provenance"], _provenance_keys(T_B_S))
    try:
        return Calibration(T_B_S=T_B_S, T_F_O=_pose(source, "T_F_O", data["T_F_O"]),
                           T_B_N=_pose(source, "T_B_N", data["T_B_N"]))
    except MessageError as exc:
        raise ConfigError(f"{source}: {exc}") from None


def read_calibration_toml(path: str | Path) -> Calibration:
    """Read a calibration TOML file. Raises :class:`~dm2.core.config.ConfigError`."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read calibration file: {exc.strerror}") from None
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path}: not a calibration file (not UTF-8 text: byte "
                          f"{exc.start})") from None
    return calibration_from_toml(text, str(path))


def read_calibration_provenance(path: str | Path) -> dict[str, str] | None:
    """The ``[provenance]`` table of a calibration file (None when it has none)."""
    path = Path(path)
    read_calibration_toml(path)  # validates the whole file
    return tomllib.loads(path.read_text(encoding="utf-8")).get("provenance")
