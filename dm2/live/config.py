"""The cell file of a live run (``dm2 monitor --live CELL.toml``): sources, calibration, limits.

Example::

    schema = 1
    name = "cold-spray cell 1"
    calibration = "calibration.toml"      # dm2.core.calibration_io format, relative to this file
    toolpath = "toolpath.csv"             # optional: layer changes without controller marks
    plate_size_mm = [120.0, 120.0, 6.0]

    [process]                             # dm2.core.config.ProcessConfig
    standoff_mm = 30.0

    [monitor]                             # dm2.core.config.MonitorConfig
    voxel_mm = 0.5

    [live]
    egm = "127.0.0.1:6510"                # UDP address the EGM stream is sent to
    egm_schema = "rw7"                    # RobotWare 7 EGM layout ("rw6": RobotWare 6)
    egm_layer_dnum = 0                    # layer index in RAPIDfromRobot.dnum[k] (RW7 only)
    controllers = ["127.0.0.1"]           # only datagrams from these addresses are used
    profiles = "127.0.0.1:6511"           # TCP address profile bridges connect to
    bridges = ["127.0.0.1"]
    bridge_idle_s = 10.0                  # a bridge connection without a frame this long: closed
    foxglove = "127.0.0.1:8765"           # the Foxglove server of --foxglove (TCP)
    allow_remote = false                  # binding a non-loopback address needs true

    [[live.scancontrol]]                  # optional: sensors driven through the vendor's
    sensor_id = "S1"                      # wrapper (dm2.live.scancontrol), besides bridges
    serial = "218020093"                  # the SDK selects sensors by serial number

Host names in ``controllers`` and ``bridges`` are resolved when the file is loaded (``localhost``
is 127.0.0.1 and ::1), so a datagram is matched against addresses; a name that does not resolve
is an error naming the key. Every model rejects unknown keys; errors are
:class:`~dm2.core.config.ConfigError` naming the file and the field (and the nearest known key).
"""

from __future__ import annotations

import ipaddress
import socket
from pathlib import Path
from typing import Literal

from pydantic import Field, ValidationError, field_validator, model_validator

from dm2.core.config import (
    SCHEMA_VERSION,
    ConfigError,
    MonitorConfig,
    ProcessConfig,
    _Model,
    check_schema_version,
    format_validation_error,
    read_toml,
)


def parse_host_port(text: str, field: str = "address") -> tuple[str, int]:
    """``"HOST:PORT"`` -> ``(host, port)``; ValueError naming ``field`` otherwise."""
    host, sep, port = str(text).rpartition(":")
    if not sep or not host:
        raise ValueError(f"{field}: expected HOST:PORT, got {text!r}")
    try:
        p = int(port)
    except ValueError:
        raise ValueError(f"{field}: port {port!r} is not a number") from None
    if not 0 <= p <= 65535:
        raise ValueError(f"{field}: port {p} outside 0..65535")
    return host, p


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def resolve_hosts(hosts, field: str) -> tuple[str, ...]:
    """IP addresses of ``hosts`` (addresses or names; ``localhost`` = 127.0.0.1 and ::1);
    ValueError naming ``field`` and the host for one that does not resolve."""
    out: list[str] = []
    for host in hosts:
        host = str(host).strip()
        try:
            addrs = [str(ipaddress.ip_address(host))]
        except ValueError:
            if host.lower() == "localhost":
                addrs = ["127.0.0.1", "::1"]
            else:
                try:
                    infos = socket.getaddrinfo(host, None, proto=socket.IPPROTO_UDP)
                except (socket.gaierror, UnicodeError, OSError):
                    raise ValueError(f"{field}: host {host!r} does not resolve to an "
                                     "address") from None
                addrs = [info[4][0] for info in infos]
        out.extend(a for a in addrs if a not in out)
    return tuple(out)


class ScanControlSensor(_Model):
    """One scanCONTROL profiler driven directly through the vendor's Python wrapper."""

    sensor_id: Literal["S1", "S2", "S3"]
    serial: str = Field(min_length=1)  # serial number, as the SDK's get_device_interfaces lists
    resolution: int = Field(640, gt=0)
    stamp: Literal["sensor", "arrival"] = "sensor"  # timestamp block or host arrival time
    exposure_us: int | None = Field(None, gt=0, multiple_of=10)  # sent in 10 us steps
    idle_us: int | None = Field(None, ge=0, multiple_of=10)

    @model_validator(mode="before")
    @classmethod
    def _no_interface(cls, data):
        if isinstance(data, dict) and "interface" in data:
            raise ValueError("interface: the scanCONTROL Linux SDK selects sensors by serial "
                             "number (get_device_interfaces lists serial numbers, not IP "
                             "addresses); write serial = \"<the sensor's serial number>\"")
        return data


class LiveConfig(_Model):
    egm: str = "127.0.0.1:6510"
    egm_schema: Literal["rw7", "rw6"] = "rw7"  # ABB RobotWare 7 (default) or 6 EGM layout
    egm_layer_dnum: int = Field(0, ge=0, le=255)  # RAPIDfromRobot.dnum index of the layer
    controllers: tuple[str, ...] = ("127.0.0.1",)
    profiles: str = "127.0.0.1:6511"
    bridges: tuple[str, ...] = ("127.0.0.1",)
    bridge_idle_s: float = Field(10.0, ge=0)  # close a bridge connection idle this long (0: never)
    foxglove: str = "127.0.0.1:8765"  # the Foxglove WebSocket server of --foxglove
    allow_remote: bool = False
    scancontrol: tuple[ScanControlSensor, ...] = ()
    max_datagram_bytes: int = Field(2048, ge=64, le=65507)
    max_frame_bytes: int = Field(28 + 10 * 4096, ge=28, le=16 << 20)
    queue_size: int = Field(20000, gt=0)
    clock_tolerance_s: float = Field(0.05, ge=0)
    max_sensor_gap_s: float = Field(1.0, gt=0)
    chunk_s: float = Field(1.0, gt=0, le=10)
    idle_stop_s: float = Field(10.0, ge=0)  # stop after data stopped this long (0: never)
    max_duration_s: float | None = Field(None, gt=0)

    @field_validator("egm", "profiles", "foxglove")
    @classmethod
    def _address(cls, v: str) -> str:
        parse_host_port(v)
        return v

    @field_validator("controllers", "bridges")
    @classmethod
    def _resolved(cls, v, info):
        return resolve_hosts(v, info.field_name)

    @model_validator(mode="after")
    def _loopback_only(self):
        if not self.allow_remote:
            for name in ("egm", "profiles", "foxglove"):
                host, _ = parse_host_port(getattr(self, name), name)
                if not is_loopback(host):
                    raise ValueError(f"{name} binds {host}, not loopback: set "
                                     f"allow_remote = true to listen on other interfaces")
        return self


class CellFile(_Model):
    """A whole live cell file."""

    schema_: int = Field(SCHEMA_VERSION, alias="schema")
    name: str = "cell"
    calibration: str
    toolpath: str | None = None
    plate_size_mm: tuple[float, float, float] = (120.0, 120.0, 6.0)
    process: ProcessConfig = ProcessConfig()
    monitor: MonitorConfig = MonitorConfig()
    live: LiveConfig = LiveConfig()

    model_config = _Model.model_config | {"populate_by_name": True}

    @field_validator("schema_")
    @classmethod
    def _schema(cls, v: int) -> int:
        return check_schema_version(v)


def load_cell_file(path: str | Path) -> CellFile:
    """Read and validate a cell file; relative paths in it resolve beside it.

    Raises ConfigError naming the file and the field.
    """
    path = Path(path)
    data = read_toml(path, "cell file")
    try:
        cell = CellFile.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(format_validation_error(str(path), exc)) from None
    update = {}
    for key in ("calibration", "toolpath"):
        value = getattr(cell, key)
        if value is not None:
            p = Path(value)
            p = p if p.is_absolute() else (path.parent / p).resolve()
            if not p.is_file():
                raise ConfigError(f"{path}: field '{key}': file {p} not found")
            update[key] = str(p)
    return cell.model_copy(update=update)
