"""MCAP recordings of the pipeline's message stream, readable by ROS 2 tools and Foxglove.

Topics (ROS 2 schemas, CDR; see :mod:`dm2.io.ros_messages` for layouts and units):

==================  ================================  =========================================
topic               type                              content
==================  ================================  =========================================
``/scan/S1..S3``    sensor_msgs/msg/PointCloud2       one profile, frame_id ``S1..``, metres
``/joint_states``   sensor_msgs/msg/JointState        ``RobotState.joints_rad``
``/tf``             tf2_msgs/msg/TFMessage            ``T_B_F`` (frame_id ``B``, child ``F``)
``/tf_static``      tf2_msgs/msg/TFMessage            ``B->N``, ``B->S1..S3``, ``F->O``
``/dm2/layer``      dm2_msgs/msg/LayerMark            layer index at its start stamp
==================  ================================  =========================================

Every message's MCAP ``log_time`` and ``publish_time`` equal its header stamp in nanoseconds.
ROS 2 headers carry no sequence number, so the 24-bit profile ``counter`` and the robot
state's ``seq`` travel, losslessly, in the MCAP message record's ``sequence`` field. A file whose
first profiles all have sequence 0 carries no counters (profiles written without one): its
profiles are read with ``counter = None`` and de-duplicated by (sensor, stamp). A
``RobotState`` is written as a ``/joint_states`` and a ``/tf`` message with the same stamp and
sequence; the reader pairs them back. Attachments make a recording self-contained:
``scenario.toml``, ``toolpath.csv`` (canonical CSV) and ``calibration.toml``
(:mod:`dm2.core.calibration_io`). Chunks close after about ``chunk_s`` of data (default 1 s), so a
crash loses at most about a second; the file is written as ``<path>.part`` and renamed on
:meth:`dm2.io.recording_writer.RecordingWriter.close`; reading is
:func:`read_recording`.
"""

from __future__ import annotations

import logging
import tempfile
from collections import Counter
from collections.abc import Iterator
from pathlib import Path

import numpy as np
from mcap.exceptions import McapError
from mcap.reader import NonSeekingReader, make_reader

from dm2.core.messages import SENSOR_IDS, Calibration, LayerMark, MessageError, Profile, RobotState
from dm2.io import ros_messages as ros
from dm2.io.mcap_integrity import (
    READ_ERRORS,
    RECOVERED_METADATA,
    SeekTracker,
    indexed_attachments,
    indexed_metadata,
    linear_extras,
    recovery_note,
    summary_intact,
)

log = logging.getLogger(__name__)

SCENARIO_ATTACHMENT = "scenario.toml"
TOOLPATH_ATTACHMENT = "toolpath.csv"
CALIBRATION_ATTACHMENT = "calibration.toml"
MEDIA_TYPES = {".toml": "application/toml", ".csv": "text/csv", ".json": "application/json"}
SCAN_TOPICS = {sid: f"/scan/{sid}" for sid in SENSOR_IDS}
JOINT_TOPIC, TF_TOPIC, TF_STATIC_TOPIC, LAYER_TOPIC = ("/joint_states", "/tf", "/tf_static",
                                                      "/dm2/layer")
MCAP_MAGIC = b"\x89MCAP0\r\n"
COUNTER_PEEK = 64  # profiles looked at to tell whether a recording carries counters


def stamp_to_ns(stamp_s: float) -> int:
    """Nanoseconds of a stamp in seconds (rounded to the nearest ns; must be >= 0)."""
    if not stamp_s >= 0.0:
        raise MessageError(f"stamp_s: recordings need stamps >= 0 s, got {stamp_s!r}")
    return round(stamp_s * 1e9)


def ns_to_stamp(stamp_ns: int) -> float:
    return stamp_ns / 1e9


class Recording:
    """A recording opened for reading (see :func:`read_recording`).

    Attributes
    ----------
    attachments : dict name -> bytes
    scenario_toml : str or None, the scenario the recording was made from
    skipped : Counter of reasons -> messages that could not be turned into pipeline messages
    complete : False when the file has no readable summary (cut short, or damaged)
    damage : None, or after a full pass of :meth:`messages` that stopped at a record it could
        not read (or a chunk that failed its CRC): ``{"error", "reason", "good_bytes",
        "offset"}`` (see :meth:`input_summary`, and :mod:`dm2.io.mcap_integrity` for what the
        CRCs cover)
    recovered : None, or the ``dm2.recovered`` record of a file ``dm2 recover`` rewrote
    bad_attachments : names of attachments left out because they fail their CRC
    """

    def __init__(self, path: Path):
        self.path = path
        self.skipped: Counter = Counter()
        self.attachments: dict[str, bytes] = {}
        self.complete = True
        self._has_counters: bool | None = None
        self.damage: dict | None = None
        self.last_stamp_ns: int | None = None  # newest log time read by a full pass
        self._linear = False
        self.summary_damaged = False  # a footer is there but the summary fails its CRC
        with open(path, "rb") as f:
            if f.read(len(MCAP_MAGIC)) != MCAP_MAGIC:
                raise ValueError(f"{path}: not an MCAP file (bad magic bytes)")
            try:
                if not summary_intact(f):
                    f.seek(-len(MCAP_MAGIC), 2)
                    self.summary_damaged = f.read() == MCAP_MAGIC  # ends properly: damaged
                    raise McapError("the summary fails its CRC")
                f.seek(0)
                reader = make_reader(f, validate_crcs=True)
                self.summary = reader.get_summary()
                if self.summary is None:  # written without one: read linearly, as it is
                    self._linear = True
                    atts, self.bad_attachments, meta = linear_extras(f)
                else:
                    atts, self.bad_attachments = indexed_attachments(f, self.summary)
                    meta = indexed_metadata(reader)
            except READ_ERRORS as exc:  # any damage to the summary: read linearly
                log.debug("%s: no usable summary (%s); reading it linearly", path, exc)
                self.complete, self.summary = False, None
                atts, self.bad_attachments, meta = linear_extras(f)
        self.attachments = atts
        rec = meta.get(RECOVERED_METADATA)
        self.recovered = recovery_note(rec) if rec is not None else None

    @property
    def scenario_toml(self) -> str | None:
        data = self.attachments.get(SCENARIO_ATTACHMENT)
        return data.decode() if data is not None else None

    @property
    def calibration(self) -> Calibration | None:
        """From ``calibration.toml`` if attached, else from ``/tf_static``, else None."""
        from dm2.core.calibration_io import calibration_from_toml

        data = self.attachments.get(CALIBRATION_ATTACHMENT)
        if data is not None:
            return calibration_from_toml(data.decode(), f"{self.path}:{CALIBRATION_ATTACHMENT}")
        return self.static_calibration()

    def static_calibration(self) -> Calibration | None:
        """The calibration as ``/tf_static`` holds it (None if incomplete or absent)."""
        poses = {}
        for _schema, _channel, message in self._iter_raw([TF_STATIC_TOPIC]):
            for _ns, parent, child, T in ros.decode_tf(message.data):
                poses[(parent, child)] = T
        sensors = {sid: poses[("B", sid)] for sid in SENSOR_IDS if ("B", sid) in poses}
        if ("B", "N") not in poses or ("F", "O") not in poses or not sensors:
            return None
        return Calibration(T_B_S=sensors, T_F_O=poses[("F", "O")], T_B_N=poses[("B", "N")])

    @property
    def toolpath(self):
        """The attached toolpath (:class:`~dm2.core.messages.Toolpath`) or None."""
        return attached_toolpath(self.attachments)

    def _iter_raw(self, topics=None):
        full = topics is None  # a full pass records how far the file could be read
        good = 0
        with open(self.path, "rb") as raw_f:
            f = SeekTracker(raw_f)
            try:
                if self.complete and not self._linear:
                    it = make_reader(f, validate_crcs=True).iter_messages(
                        topics=topics, log_time_order=True)
                else:
                    it = NonSeekingReader(f, validate_crcs=True).iter_messages(
                        topics=topics, log_time_order=False)
                for item in it:
                    if full:
                        t = item[2].log_time
                        if self.last_stamp_ns is None or t > self.last_stamp_ns:
                            self.last_stamp_ns = t
                        good = f.tell()
                    yield item
            except READ_ERRORS as exc:
                why = str(exc) or type(exc).__name__
                log.debug("%s: stopped at a record it cannot read (%s)", self.path, why)
                if full:  # indexed: the chunk last sought to; linear: after the last good one
                    indexed = self.complete and not self._linear
                    at = max(0, f.last_seek - 9) if indexed else good
                    self.damage = {"error": type(exc).__name__, "reason": why[:200],
                                   "good_bytes": int(good), "offset": int(at)}

    def input_summary(self) -> dict:
        """What the full pass of :meth:`messages` read: ``complete`` (False when it stopped at
        a record it could not read, an attachment failed its CRC, or the file was recovered
        from a cut or damaged one),
        ``truncated`` (no usable summary: cut short), ``last_stamp_s`` (newest message read),
        ``bytes_skipped`` (bytes after the last chunk read), ``stopped_at_byte`` and
        ``stopped_at_stamp_s`` (where the reading stopped), ``recovered`` (the record
        ``dm2 recover`` left), ``bad_attachments`` (left out: they fail their CRC)."""
        size = self.path.stat().st_size
        damaged = self.damage is not None
        skipped = max(0, size - self.damage["good_bytes"]) if damaged else 0
        last = None if self.last_stamp_ns is None else ns_to_stamp(self.last_stamp_ns)
        rec = self.recovered
        lost = rec is not None and not (rec.get("complete") == "true" and rec["intact"])
        out = {"file": str(self.path),
               "complete": not (damaged or lost or self.bad_attachments
                                or self.summary_damaged),
               "truncated": damaged and not self.complete, "indexed": self.complete,
               "last_stamp_s": last, "bytes": size, "bytes_skipped": skipped,
               "error": self.damage["error"] if damaged else None}
        if damaged:
            out.update(stopped_at_byte=self.damage["offset"], stopped_at_stamp_s=last,
                       reason=self.damage["reason"])
        if self.recovered is not None:
            out["recovered"] = self.recovered
        if self.summary_damaged:
            out["summary_damaged"] = True
        if self.bad_attachments:
            out["bad_attachments"] = list(self.bad_attachments)
        return out

    @property
    def has_counters(self) -> bool:
        """False when the first ``COUNTER_PEEK`` profiles all have sequence 0."""
        if self._has_counters is None:
            seqs = []
            raw = self._iter_raw(list(SCAN_TOPICS.values()))
            for _schema, _channel, message in raw:
                seqs.append(message.sequence)
                if len(seqs) >= COUNTER_PEEK:
                    break
            raw.close()
            self._has_counters = any(seqs)
        return self._has_counters

    def robot_poses(self) -> Iterator[tuple[float, np.ndarray]]:
        """``(stamp_s, T_B_F)`` of every robot state, decoding only ``/tf`` (file order)."""
        for _schema, _channel, message in self._iter_raw([TF_TOPIC]):
            try:
                for ns, parent, child, T in ros.decode_tf(message.data):
                    if (parent, child) == ("B", "F"):
                        yield ns_to_stamp(ns), T
            except (ros.CdrError, ValueError):
                continue

    def layer_marks(self) -> Iterator[tuple[float, int]]:
        """``(stamp_s, layer)`` of every layer mark, decoding only ``/dm2/layer``."""
        for _schema, _channel, message in self._iter_raw([LAYER_TOPIC]):
            try:
                ns, layer = ros.decode_layer_mark(message.data)
            except (ros.CdrError, ValueError):
                continue
            yield ns_to_stamp(ns), layer

    def messages(self) -> Iterator[Profile | RobotState | LayerMark]:
        """Pipeline messages in stamp order (a RobotState once its joints and pose both came)."""
        scan_ids = {t: sid for sid, t in SCAN_TOPICS.items()}
        counters = self.has_counters
        if not counters:
            log.info("%s: no profile counters (every MCAP sequence is 0); duplicate profiles "
                     "are recognised by (sensor, stamp)", self.path)
        pending_joints: dict[int, tuple] = {}
        pending_tf: dict[int, tuple] = {}
        for _schema, channel, message in self._iter_raw():
            topic = channel.topic
            try:
                if topic in scan_ids:
                    ns, frame_id, xz, valid, inten = ros.decode_cloud(message.data)
                    yield Profile(scan_ids[topic], ns_to_stamp(ns),
                                  message.sequence if counters else None, xz, valid, inten)
                elif topic == JOINT_TOPIC:
                    ns, _names, pos = ros.decode_joint_state(message.data)
                    state = self._pair(ns, message.sequence, pending_tf, pending_joints, pos)
                    if state is not None:
                        yield state
                elif topic == TF_TOPIC:
                    for ns, parent, child, T in ros.decode_tf(message.data):
                        if (parent, child) == ("B", "F"):
                            state = self._pair(ns, message.sequence, pending_joints,
                                               pending_tf, T, joints_first=False)
                            if state is not None:
                                yield state
                elif topic == LAYER_TOPIC:
                    ns, layer = ros.decode_layer_mark(message.data)
                    yield LayerMark(ns_to_stamp(ns), layer)
            except (ros.CdrError, MessageError, ValueError) as exc:
                self.skipped[f"{topic}: {type(exc).__name__}"] += 1
                log.debug("%s: skipped a %s message: %s", self.path, topic, exc)
        unpaired = len(pending_joints) + len(pending_tf)
        if unpaired:
            self.skipped["robot state without both /joint_states and /tf"] += unpaired

    @staticmethod
    def _pair(ns, seq, other: dict, mine: dict, value, joints_first: bool = True):
        partner = other.pop(ns, None)
        if partner is None:
            mine[ns] = (seq, value)
            return None
        joints, T = (value, partner[1]) if joints_first else (partner[1], value)
        return RobotState(ns_to_stamp(ns), seq, joints, T)


def attached_toolpath(attachments: dict[str, bytes]):
    """The ``toolpath.csv`` attachment as a :class:`~dm2.core.messages.Toolpath`, or None."""
    data = attachments.get(TOOLPATH_ATTACHMENT)
    if data is None:
        return None
    from dm2.toolpath.formats import read_csv

    with tempfile.TemporaryDirectory() as tmp:
        p = Path(tmp) / TOOLPATH_ATTACHMENT
        p.write_bytes(data)
        return read_csv(p)


def read_recording(path: str | Path) -> Recording:
    """Open an MCAP recording. Raises FileNotFoundError / ValueError naming the file."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: recording not found")
    try:
        return Recording(path)
    except McapError as exc:
        raise ValueError(f"{path}: not a readable MCAP recording: {exc}") from None
