"""The map from a foreign recording's topic and frame names onto the pipeline's names.

``dm2 monitor REC --map MAP.toml`` reads a recording made by the cell itself (``ros2 bag
record``) through this map. The format::

    [topics]
    profiles = { S1 = "/scanners/left/points", S2 = "/scanners/rear/points", S3 = "/scanners/right/points" }
    tf = "/tf"                    # default "/tf"
    tf_static = "/tf_static"      # default "/tf_static"
    joint_states = "/joint_states"  # optional
    layer = "/dm2/layer"          # optional; without it layers come from the toolpath or one layer
    [frames]
    base = "base_link"
    flange = "tool0"
    work_object = "plate"
    nozzle = "nozzle_exit"
    sensors = { S1 = "scanner_left", S2 = "scanner_rear", S3 = "scanner_right" }

``profiles`` and ``sensors`` name the same sensors (a subset of ``S1..S3``). Without a map, a
recording is read in the pipeline's own names (:data:`PROJECT_MAP`). A bad map raises
:class:`MapError`, whose text names the key and lists what the recording offers.
"""  # noqa: E501

from __future__ import annotations

import tomllib
from dataclasses import dataclass, field
from pathlib import Path

from dm2.core.messages import SENSOR_IDS


class MapError(ValueError):
    """A map key is missing, unknown, or names something the recording does not have."""


@dataclass(frozen=True)
class RecordingMap:
    """Pipeline name -> recording name (see the module docstring)."""

    profiles: dict[str, str]
    sensors: dict[str, str]
    base: str = "B"
    flange: str = "F"
    work_object: str = "O"
    nozzle: str = "N"
    tf: str = "/tf"
    tf_static: str = "/tf_static"
    joint_states: str | None = None
    layer: str | None = None
    source: str = "the pipeline's own names"
    optional_topics_required: bool = field(default=True)  # False: absent optional topics are ok

    def frame_keys(self) -> dict[str, str]:
        """``map key -> frame`` for every frame the map names."""
        keys = {"frames.base": self.base, "frames.flange": self.flange,
                "frames.work_object": self.work_object, "frames.nozzle": self.nozzle}
        keys.update({f"frames.sensors.{sid}": f for sid, f in self.sensors.items()})
        return keys

    def check_topics(self, offered: dict[str, str]) -> None:
        """Raise MapError for a mapped topic the recording lacks (``offered``: topic -> type)."""
        listing = ", ".join(f"{t} ({offered[t]})" for t in sorted(offered)) or "none"
        wanted = {f"topics.profiles.{sid}": t for sid, t in self.profiles.items()}
        wanted["topics.tf"] = self.tf
        for key, topic in (("topics.joint_states", self.joint_states),
                           ("topics.layer", self.layer)):
            if topic is not None and self.optional_topics_required:
                wanted[key] = topic
        for key, topic in wanted.items():
            if topic not in offered:
                raise MapError(f"{self.source}: {key} = {topic!r}: the recording has no such "
                               f"topic; it has: {listing}")
        if self.tf_static in offered:
            wanted["topics.tf_static"] = self.tf_static
        for key, topic in wanted.items():
            kinds = _TOPIC_TYPES[key.split(".")[1]]
            if offered[topic] not in kinds:
                raise MapError(f"{self.source}: {key} = {topic!r} is a {offered[topic]}, not a "
                               f"{' or '.join(kinds)}")

    def check_frames(self, keys: list[str], offered: list[str]) -> None:
        """Raise MapError for a frame (of the map ``keys``) the tf tree lacks."""
        names = self.frame_keys()
        for key in keys:
            if names[key] not in offered:
                raise MapError(f"{self.source}: {key} = {names[key]!r}: the recording's tf tree "
                               f"has no such frame; it has: {', '.join(offered) or 'none'}")


PROJECT_MAP = RecordingMap(profiles={sid: f"/scan/{sid}" for sid in SENSOR_IDS},
                           sensors={sid: sid for sid in SENSOR_IDS},
                           joint_states="/joint_states", layer="/dm2/layer",
                           optional_topics_required=False)

_TOPIC_KEYS = {"profiles", "tf", "tf_static", "joint_states", "layer"}
_TF = ("tf2_msgs/msg/TFMessage",)
# the message types each topic key can be read as (a layer mark: ours, or a bare integer)
_TOPIC_TYPES = {"profiles": ("sensor_msgs/msg/PointCloud2",), "tf": _TF, "tf_static": _TF,
                "joint_states": ("sensor_msgs/msg/JointState",),
                "layer": ("dm2_msgs/msg/LayerMark",) + tuple(
                    f"std_msgs/msg/{k}" for k in ("Int32", "UInt32", "Int64", "UInt64",
                                                  "Int16", "UInt16", "Int8", "UInt8"))}
_FRAME_KEYS = {"base", "flange", "work_object", "nozzle", "sensors"}


def _str(where: str, key: str, value) -> str:
    if not isinstance(value, str) or not value:
        raise MapError(f"{where}: {key} must be a non-empty string, got {value!r}")
    return value


def _sensor_table(where: str, key: str, value) -> dict[str, str]:
    if not isinstance(value, dict) or not value:
        raise MapError(f"{where}: {key} must be a table of sensors, e.g. "
                       f"{{ S1 = \"...\" }}, got {value!r}")
    for sid in value:
        if sid not in SENSOR_IDS:
            raise MapError(f"{where}: {key}.{sid}: unknown sensor (the pipeline's sensors are "
                           f"{', '.join(SENSOR_IDS)})")
    return {sid: _str(where, f"{key}.{sid}", v) for sid, v in value.items()}


def parse_map(data: dict, where: str) -> RecordingMap:
    """A RecordingMap from the parsed TOML ``data`` (``where`` names the file in errors)."""
    unknown = sorted(set(data) - {"topics", "frames"})
    if unknown:
        raise MapError(f"{where}: unknown table [{unknown[0]}] (a map has [topics] and [frames])")
    for table in ("topics", "frames"):
        if not isinstance(data.get(table), dict):
            raise MapError(f"{where}: missing table [{table}]")
    topics, frames = data["topics"], data["frames"]
    for table, allowed, got in (("topics", _TOPIC_KEYS, topics), ("frames", _FRAME_KEYS, frames)):
        extra = sorted(set(got) - allowed)
        if extra:
            raise MapError(f"{where}: unknown key {table}.{extra[0]} (allowed: "
                           f"{', '.join(sorted(allowed))})")
    for key in ("profiles",):
        if key not in topics:
            raise MapError(f"{where}: missing key topics.{key}")
    for key in ("base", "flange", "work_object", "nozzle", "sensors"):
        if key not in frames:
            raise MapError(f"{where}: missing key frames.{key}")
    profiles = _sensor_table(where, "topics.profiles", topics["profiles"])
    sensors = _sensor_table(where, "frames.sensors", frames["sensors"])
    if set(profiles) != set(sensors):
        raise MapError(f"{where}: topics.profiles names sensors {sorted(profiles)} but "
                       f"frames.sensors names {sorted(sensors)}; they must be the same")
    opt = {k: _str(where, f"topics.{k}", topics[k]) for k in ("joint_states", "layer")
           if k in topics}
    return RecordingMap(
        profiles=profiles, sensors=sensors,
        base=_str(where, "frames.base", frames["base"]),
        flange=_str(where, "frames.flange", frames["flange"]),
        work_object=_str(where, "frames.work_object", frames["work_object"]),
        nozzle=_str(where, "frames.nozzle", frames["nozzle"]),
        tf=_str(where, "topics.tf", topics.get("tf", "/tf")),
        tf_static=_str(where, "topics.tf_static", topics.get("tf_static", "/tf_static")),
        joint_states=opt.get("joint_states"), layer=opt.get("layer"), source=where)


def read_map(path: str | Path) -> RecordingMap:
    """Read a map TOML file (MapError / FileNotFoundError name the file)."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise FileNotFoundError(f"--map {path}: file not found") from None
    except OSError as exc:
        raise MapError(f"--map {path}: cannot read: {exc.strerror}") from None
    except UnicodeDecodeError as exc:
        raise MapError(f"--map {path}: not a map (not UTF-8 text: byte {exc.start})") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise MapError(f"--map {path}: not valid TOML: {exc}") from None
    return parse_map(data, f"--map {path}")
