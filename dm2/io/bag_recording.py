"""Recordings the cell made itself: rosbag2 bag folders (``metadata.yaml`` with one or more
``.mcap`` or ``.db3`` files, split bags), single ``.mcap`` or ``.db3`` files, in the pipeline's
names or in the cell's own through a :class:`~dm2.io.recording_map.RecordingMap`.

Read with ``rosbags`` (containers and CDR of any message type). The tf tree (``/tf`` and
``/tf_static``) is read first into a :class:`~dm2.io.tf_buffer.TfBuffer`; then every profile
becomes a robot state at its stamp, ``T_B_F`` resolved through the tree (each dynamic edge
interpolated at the stamp), and the profile itself. A profile whose lookup would extrapolate a
dynamic edge beyond ``max_pose_gap_s`` is dropped and counted. rosbag2 stores no profile
counter, so profiles carry none and the pipeline de-duplicates them by (sensor, stamp).

:func:`open_recording` opens any recording: the project's own MCAP files (written by
:class:`~dm2.io.recording_writer.RecordingWriter`) through :mod:`dm2.io.recording`, with their
counters, everything else here.
"""

from __future__ import annotations

import logging
from collections import Counter, deque
from pathlib import Path

import numpy as np

from dm2.core.messages import Calibration, LayerMark, MessageError, Profile, RobotState
from dm2.io import recording as own
from dm2.io.pointcloud import PLANE_TOL_MM, CloudError, cloud_xyz, profile_points
from dm2.io.recording_map import PROJECT_MAP, MapError, RecordingMap
from dm2.io.ros_messages import MM_PER_M
from dm2.io.tf_buffer import TfBuffer, TfError

log = logging.getLogger(__name__)
OFF_PLANE_TOPIC_FRACTION = 0.9  # a topic this much off its sensor's plane is named
_OWN_MARK = b"dm2 recording"  # the metadata record RecordingWriter writes after the header


def _stamp_s(stamp) -> float:
    return stamp.sec + stamp.nanosec * 1e-9


def _matrix(tf) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    q, t = tf.rotation, tf.translation
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix()
    T[:3, 3] = np.array([t.x, t.y, t.z]) * MM_PER_M
    return T


class BagRecording:
    """A rosbag2 recording opened for reading (the interface of :class:`dm2.io.recording.
    Recording`: ``messages()``, ``calibration``, ``toolpath``, ``scenario_toml``,
    ``skipped``), plus ``problems``: messages about whole topics that gave nothing."""

    def __init__(self, path: Path, rmap: RecordingMap = PROJECT_MAP,
                 max_pose_gap_s: float = 0.05):
        from rosbags.highlevel import AnyReader, AnyReaderError
        from rosbags.rosbag2 import ReaderError
        from rosbags.typesys import Stores, get_typestore

        self.path, self.map, self.max_pose_gap_s = path, rmap, float(max_pose_gap_s)
        self.skipped: Counter = Counter()
        self.problems: list[str] = []
        self._reader = AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
        try:
            self._reader.open()
        except (AnyReaderError, ReaderError, OSError, KeyError, ValueError) as exc:
            raise ValueError(f"{path}: not a readable rosbag2 recording: {exc}") from None
        self.topics = {c.topic: c.msgtype for c in self._reader.connections}
        rmap.check_topics(self.topics)
        self.attachments = self._mcap_attachments()
        self.tf = self._read_tf()
        offered = self.tf.frames
        rmap.check_frames(["frames.base", "frames.flange"], offered)
        try:
            self.tf.path(rmap.base, rmap.flange)
        except TfError as exc:
            raise MapError(f"{rmap.source}: frames.base -> frames.flange: {exc}") from None

    def close(self) -> None:
        """Close the bag's files (reading again afterwards raises)."""
        if self._reader.stack is not None:
            self._reader.close()

    def _connections(self, topics) -> list:
        return [c for c in self._reader.connections if c.topic in topics]

    def _mcap_attachments(self) -> dict[str, bytes]:
        from mcap.reader import make_reader

        files = sorted(self.path.glob("*.mcap")) if self.path.is_dir() else [self.path]
        out: dict[str, bytes] = {}
        for f in files:
            if f.suffix != ".mcap":
                continue
            try:
                with open(f, "rb") as fh:
                    out.update({a.name: bytes(a.data) for a in make_reader(fh).iter_attachments()})
            except Exception as exc:  # noqa: BLE001 - attachments are optional extras
                log.debug("%s: no attachments read (%s)", f, exc)
        return out

    def _read_tf(self) -> TfBuffer:
        tf = TfBuffer()
        m = self.map
        for conn, _ts, raw in self._reader.messages(self._connections({m.tf, m.tf_static})):
            static = conn.topic == m.tf_static
            try:
                msg = self._reader.deserialize(raw, conn.msgtype)
                for tr in msg.transforms:
                    tf.add(_stamp_s(tr.header.stamp), tr.header.frame_id, tr.child_frame_id,
                           _matrix(tr.transform), static, f"{self.path}: {conn.topic}")
            except TfError:
                raise
            except Exception as exc:  # noqa: BLE001 - a foreign message we cannot read
                self.skipped[f"{conn.topic}: {type(exc).__name__}"] += 1
        tf.finish()
        return tf

    @property
    def scenario_toml(self) -> str | None:
        data = self.attachments.get(own.SCENARIO_ATTACHMENT)
        return data.decode() if data is not None else None

    @property
    def toolpath(self):
        """The attached toolpath (MCAP storage only) or None."""
        return own.attached_toolpath(self.attachments)

    @property
    def calibration(self) -> Calibration | None:
        from dm2.core.calibration_io import calibration_from_toml

        data = self.attachments.get(own.CALIBRATION_ATTACHMENT)
        if data is not None:
            return calibration_from_toml(data.decode(),
                                         f"{self.path}:{own.CALIBRATION_ATTACHMENT}")
        return self.static_calibration()

    def static_calibration(self) -> Calibration:
        """Sensor, nozzle and work-object poses from the tf tree (they must be static: the
        sensors and the nozzle relative to the base, the work object relative to the flange)."""
        m = self.map
        keys = ["frames.nozzle", "frames.work_object"] + [f"frames.sensors.{s}"
                                                          for s in m.sensors]
        m.check_frames(keys, self.tf.frames)
        frames = m.frame_keys()

        def static(key: str, parent_key: str) -> np.ndarray:
            parent, child = frames[parent_key], frames[key]
            try:
                dyn = self.tf.dynamic_edges(parent, child, moving_only=True)
            except TfError as exc:
                raise MapError(f"{m.source}: {key} = {child!r}: {exc}") from None
            if dyn:
                edges = ", ".join(f"{a} -> {b}" for a, b in dyn)
                what = ("the sensors and the nozzle stay fixed relative to the robot base (the "
                        "robot moves the substrate)" if parent_key == "frames.base" else
                        "the work object is fixed on the flange")
                raise MapError(f"{self.path}: {key} = {child!r} moves relative to {parent_key} "
                               f"= {parent!r}: its tf path holds the dynamic edge(s) {edges} "
                               f"on {m.tf}; dm2 expects {what}")
            return self.tf.lookup(parent, child)  # fixed edges on /tf: their nearest sample

        T_B_S = {sid: static(f"frames.sensors.{sid}", "frames.base") for sid in m.sensors}
        return Calibration(T_B_S=T_B_S, T_F_O=static("frames.work_object", "frames.flange"),
                           T_B_N=static("frames.nozzle", "frames.base"))

    def _T_S_C(self, sid: str, frame_id: str, cache: dict) -> np.ndarray | None | bool:
        """Sensor <- cloud frame (None: the same frame; False: not statically connected)."""
        key = (sid, frame_id)
        if key not in cache:
            sensor = self.map.sensors[sid]
            if frame_id in ("", sensor):
                cache[key] = None
            else:
                try:
                    ok = not self.tf.dynamic_edges(sensor, frame_id, moving_only=True)
                except TfError:
                    ok = False
                cache[key] = self.tf.lookup(sensor, frame_id) if ok else False
                if ok:
                    log.info("%s: %s clouds come in frame %r; transformed into %r", self.path,
                             sid, frame_id, sensor)
        return cache[key]

    def messages(self):
        """Pipeline messages: RobotState and Profile per profile stamp, LayerMark."""
        m = self.map
        sid_of = {t: sid for sid, t in m.profiles.items()}
        extra = {t for t in (m.joint_states, m.layer) if t is not None and t in self.topics}
        log.info("%s: no profile counters in a rosbag2 recording; duplicate profiles are "
                 "recognised by (sensor, stamp)", self.path)
        joints = np.zeros(6)
        recent: deque = deque(maxlen=256)
        recent_set: set[float] = set()
        frames_cache: dict = {}
        per_topic = {t: Counter() for t in sid_of}
        seq = 0
        reader = self._reader
        for conn, ts_ns, raw in reader.messages(self._connections(set(sid_of) | extra)):
            topic = conn.topic
            try:
                msg = reader.deserialize(raw, conn.msgtype)
                if topic == m.joint_states:
                    pos = np.asarray(msg.position, dtype=np.float64)[:6]
                    joints = np.concatenate([pos, np.zeros(6 - pos.size)])
                    continue
                if topic == m.layer:
                    stamp = _stamp_s(msg.stamp) if hasattr(msg, "stamp") else ts_ns * 1e-9
                    yield LayerMark(stamp, int(msg.layer if hasattr(msg, "layer") else msg.data))
                    continue
                sid = sid_of[topic]
                stamp = _stamp_s(msg.header.stamp)
                frame_id = msg.header.frame_id.lstrip("/")
                T_S_C = self._T_S_C(sid, frame_id, frames_cache)
                if T_S_C is False:
                    self.skipped[f"{topic}: cloud frame {frame_id!r} not fixed to "
                                 f"{m.sensors[sid]!r}"] += 1
                    continue
                xyz, inten = cloud_xyz(msg)
                xz, valid, n_off = profile_points(xyz, T_S_C)
                per_topic[topic]["valid"] += int(valid.sum())
                per_topic[topic]["off_plane"] += n_off
                if n_off:
                    self.skipped["off_plane_points"] += n_off
                T_B_F = self.tf.lookup(m.base, m.flange, stamp, self.max_pose_gap_s)
                if T_B_F is None:
                    self.skipped["tf lookup beyond max_pose_gap_s"] += 1
                    continue
                if stamp not in recent_set:
                    if len(recent) == recent.maxlen:
                        recent_set.discard(recent[0])
                    recent.append(stamp)
                    recent_set.add(stamp)
                    yield RobotState(stamp, seq, joints, T_B_F)
                    seq += 1
                yield Profile(sid, stamp, None, xz, valid, inten)
            except (CloudError, MessageError, AttributeError, TypeError, ValueError) as exc:
                self.skipped[f"{topic}: {type(exc).__name__}"] += 1
                log.debug("%s: skipped a %s message: %s", self.path, topic, exc)
        for topic, c in per_topic.items():
            n = c["off_plane"] + c["valid"]
            if n and c["off_plane"] >= OFF_PLANE_TOPIC_FRACTION * n:
                sid = sid_of[topic]
                self._problem(f"{topic}: {c['off_plane']} of its {n} points "
                              f"({100 * c['off_plane'] / n:.0f} %) lie off the x-z plane of "
                              f"frames.sensors.{sid} = {m.sensors[sid]!r} (|y| > "
                              f"{PLANE_TOL_MM} mm) and were dropped: the clouds' frame is "
                              "probably not that sensor's")

    def _problem(self, text: str) -> None:
        if text not in self.problems:
            self.problems.append(text)
            log.warning("%s", text)


def is_own_recording(path: Path) -> bool:
    """Whether ``path`` is an MCAP file the project's RecordingWriter wrote."""
    if not path.is_file():
        return False
    with open(path, "rb") as f:
        head = f.read(4096)
    return head.startswith(own.MCAP_MAGIC) and _OWN_MARK in head


def open_recording(path: str | Path, rmap: RecordingMap | None = None,
                   max_pose_gap_s: float = 0.05):
    """Open a recording: the project's own MCAP (without a map), a rosbag2 folder, ``.mcap``
    or ``.db3``. Raises FileNotFoundError / ValueError / MapError naming the file or key."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: recording not found")
    if rmap is None and is_own_recording(path):
        return own.read_recording(path)
    if path.is_dir() and not (path / "metadata.yaml").is_file():
        raise ValueError(f"{path}: a folder but not a rosbag2 bag (no metadata.yaml)")
    if path.is_file() and path.suffix not in (".mcap", ".db3"):
        raise ValueError(f"{path}: not a recording (expected an .mcap or .db3 file or a rosbag2 "
                         "folder)")
    return BagRecording(path, rmap or PROJECT_MAP, max_pose_gap_s)
