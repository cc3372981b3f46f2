"""Writing MCAP recordings of the pipeline's message stream (format: :mod:`dm2.io.recording`)."""

from __future__ import annotations

from collections import Counter
from pathlib import Path

from mcap.writer import CompressionType, Writer

from dm2.core.messages import Calibration, LayerMark, MessageError, Profile, RobotState
from dm2.io import ros_messages as ros
from dm2.io.recording import (
    CALIBRATION_ATTACHMENT,
    JOINT_TOPIC,
    LAYER_TOPIC,
    MEDIA_TYPES,
    SCAN_TOPICS,
    TF_STATIC_TOPIC,
    TF_TOPIC,
    stamp_to_ns,
)

SAFETY_CHUNK_BYTES = 16 * 1024 * 1024  # a chunk closes at this size even within chunk_s
_U32 = 1 << 32


class RecordingWriter:
    """Write pipeline messages to an MCAP file.

    Parameters
    ----------
    path : output file; written as ``<path>.part`` and renamed by :meth:`close`
    attachments : name -> bytes stored as MCAP attachments (``scenario.toml``, ...)
    chunk_s : float [s], a chunk is closed once it spans this much message time
    """

    def __init__(self, path: str | Path, *, attachments: dict[str, bytes] | None = None,
                 chunk_s: float = 1.0):
        if chunk_s <= 0:
            raise ValueError(f"chunk_s must be positive, got {chunk_s}")
        self.path = Path(path)
        self.part_path = self.path.with_name(self.path.name + ".part")
        self._file = open(self.part_path, "wb")  # noqa: SIM115 (closed in close())
        self._mcap = Writer(self._file, chunk_size=SAFETY_CHUNK_BYTES,
                            compression=CompressionType.ZSTD)
        self._mcap.start(profile="ros2", library="dm2")
        self._mcap.add_metadata("dm2", {"format": "dm2 recording", "version": "1",
                                        "counter": "MCAP message sequence"})
        self._chunk_ns = round(chunk_s * 1e9)
        self._chunk_start_ns: int | None = None
        self._schemas = {name: self._mcap.register_schema(name, "ros2msg", text.encode())
                         for name, text in ros.SCHEMAS.items()}
        self._channels: dict[str, int] = {}
        self._attachment_names: set[str] = set()
        self.counts: Counter = Counter()
        self._closed = False
        for name, data in (attachments or {}).items():
            self.add_attachment(name, data)

    def add_attachment(self, name: str, data: bytes | str) -> None:
        """Store ``data`` as attachment ``name`` (media type from the suffix)."""
        if isinstance(data, str):
            data = data.encode()
        media = MEDIA_TYPES.get(Path(name).suffix, "application/octet-stream")
        self._mcap.add_attachment(create_time=0, log_time=0, name=name, media_type=media,
                                  data=bytes(data))
        self._attachment_names.add(name)

    def _channel(self, topic: str, schema: str) -> int:
        cid = self._channels.get(topic)
        if cid is None:
            cid = self._mcap.register_channel(topic, "cdr", self._schemas[schema])
            self._channels[topic] = cid
        return cid

    def _add(self, topic: str, schema: str, stamp_ns: int, data: bytes, sequence: int = 0):
        if self._closed:
            raise ValueError(f"{self.path}: recording already closed")
        if self._chunk_start_ns is None:
            self._chunk_start_ns = stamp_ns
        elif abs(stamp_ns - self._chunk_start_ns) >= self._chunk_ns:
            self._mcap.flush()  # closes the chunk and pushes it to disk
            self._chunk_start_ns = stamp_ns
        self._mcap.add_message(self._channel(topic, schema), log_time=stamp_ns, data=data,
                               publish_time=stamp_ns, sequence=sequence)
        self.counts[topic] += 1

    def write_profile(self, p: Profile) -> None:
        ns = stamp_to_ns(p.stamp_s)
        data = ros.encode_cloud(ns, p.sensor_id, p.xz_S, p.valid, p.intensity)
        self._add(SCAN_TOPICS[p.sensor_id], ros.POINTCLOUD2, ns, data,
                  0 if p.counter is None else p.counter)  # no counter: sequence 0

    def write_robot_state(self, s: RobotState) -> None:
        if not 0 <= s.seq < _U32:
            raise MessageError(f"RobotState.seq: {s.seq} does not fit 32 bits unsigned")
        ns = stamp_to_ns(s.stamp_s)
        self._add(JOINT_TOPIC, ros.JOINTSTATE, ns, ros.encode_joint_state(ns, s.joints_rad), s.seq)
        self._add(TF_TOPIC, ros.TFMESSAGE, ns, ros.encode_tf([(ns, "B", "F", s.T_B_F)]), s.seq)

    def write_layer_mark(self, m: LayerMark) -> None:
        ns = stamp_to_ns(m.stamp_s)
        self._add(LAYER_TOPIC, ros.LAYERMARK, ns, ros.encode_layer_mark(ns, m.layer))

    def write_static_tf(self, calibration: Calibration, stamp_s: float = 0.0) -> None:
        """Write the calibration on ``/tf_static`` (and as ``calibration.toml`` if absent)."""
        from dm2.core.calibration_io import calibration_to_toml

        ns = stamp_to_ns(stamp_s)
        tfs = [(ns, "B", "N", calibration.T_B_N)]
        tfs += [(ns, "B", sid, T) for sid, T in sorted(calibration.T_B_S.items())]
        tfs.append((ns, "F", "O", calibration.T_F_O))
        self._add(TF_STATIC_TOPIC, ros.TFMESSAGE, ns, ros.encode_tf(tfs))
        if CALIBRATION_ATTACHMENT not in self._attachment_names:
            self.add_attachment(CALIBRATION_ATTACHMENT, calibration_to_toml(calibration))

    def write(self, msg: Profile | RobotState | LayerMark) -> None:
        """Write any pipeline message."""
        if isinstance(msg, Profile):
            self.write_profile(msg)
        elif isinstance(msg, RobotState):
            self.write_robot_state(msg)
        elif isinstance(msg, LayerMark):
            self.write_layer_mark(msg)
        else:
            raise TypeError(f"cannot record {type(msg).__name__}")

    def close(self, keep_part: bool = False) -> Path:
        """Finish the file and rename it into place (``keep_part``: leave it as ``.part``)."""
        if not self._closed:
            self._closed = True
            self._mcap.finish()
            self._file.close()
            if not keep_part:
                self.part_path.replace(self.path)
        return self.part_path if keep_part else self.path

    def __enter__(self) -> RecordingWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        self.close(keep_part=exc_type is not None)
