"""ROS 2 message schemas of dm2 recordings and their CDR encoding.

Recordings use the standard ROS 2 types so that Foxglove and ROS 2 tools open them:

- ``sensor_msgs/msg/PointCloud2`` for profiles: ``height = 1``, ``width = n`` points, fields
  ``x, y, z, intensity`` (FLOAT32, little endian, ``point_step = 16``), coordinates in metres
  in the sensor frame (``y = 0``, the laser plane), invalid points written as NaN so the point
  count and validity survive (``is_dense = False``).
- ``sensor_msgs/msg/JointState`` for joints (``joint_1 .. joint_6``, radians).
- ``tf2_msgs/msg/TFMessage`` for ``/tf`` and ``/tf_static`` (translations in metres).
- ``dm2_msgs/msg/LayerMark`` (``builtin_interfaces/Time stamp``, ``int32 layer``).

Every message is encoded and decoded by ``rosbags`` (:mod:`dm2.io.cdr`), except the
PointCloud2 encoder, kept hand-written because ``benchmarks/cdr.py`` (1280 points a profile)
measures it at about half rosbags' time on the hot path, one message per profile at the
scanners' rate: 0.52x for the former CDR writer (36 against 69 µs a profile), 0.46x for this
template (41 against 90 µs). It fills a per-frame template that rosbags serialized, so the bytes
are rosbags' own. The JointState encoder of six joints fills a template the same way: at the
controller's 250 Hz it is on the recording's hot path too (``benchmarks/twin.py``: the recorded
twin stream ran at 14-15x real time with rosbags' encoder against 19-21x before). The former
hand-written TFMessage and LayerMark encoders were faster as well (0.62x, 0.45x) but saved a few
µs a message, and the former decoders were no faster than rosbags (0.83x to 0.97x: the
conversion to numpy costs the same either way), so those were replaced.
"""

from __future__ import annotations

import math
import struct
from functools import cache

import numpy as np

from dm2.io.cdr import (
    LAYERMARK,
    LAYERMARK_DEF,
    CdrError,
    deserialize,
    header,
    msg_class,
    ros_time,
    serialize,
    split_ns,
    stamp_ns,
)

__all__ = ["CdrError", "LAYERMARK", "LAYERMARK_DEF"]

SEP = "=" * 80 + "\n"
HEADER_DEF = "MSG: std_msgs/Header\nbuiltin_interfaces/Time stamp\nstring frame_id\n"

POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
POINTCLOUD2_DEF = (
    "std_msgs/Header header\nuint32 height\nuint32 width\nsensor_msgs/PointField[] fields\n"
    "bool is_bigendian\nuint32 point_step\nuint32 row_step\nuint8[] data\nbool is_dense\n"
    + SEP + HEADER_DEF + SEP
    + "MSG: sensor_msgs/PointField\nuint8 INT8=1\nuint8 UINT8=2\nuint8 INT16=3\n"
    "uint8 UINT16=4\nuint8 INT32=5\nuint8 UINT32=6\nuint8 FLOAT32=7\nuint8 FLOAT64=8\n"
    "string name\nuint32 offset\nuint8 datatype\nuint32 count\n")

JOINTSTATE = "sensor_msgs/msg/JointState"
JOINTSTATE_DEF = ("std_msgs/Header header\nstring[] name\nfloat64[] position\n"
                  "float64[] velocity\nfloat64[] effort\n" + SEP + HEADER_DEF)

TFMESSAGE = "tf2_msgs/msg/TFMessage"
TFMESSAGE_DEF = (
    "geometry_msgs/TransformStamped[] transforms\n" + SEP
    + "MSG: geometry_msgs/TransformStamped\nstd_msgs/Header header\nstring child_frame_id\n"
    "geometry_msgs/Transform transform\n" + SEP + HEADER_DEF + SEP
    + "MSG: geometry_msgs/Transform\ngeometry_msgs/Vector3 translation\n"
    "geometry_msgs/Quaternion rotation\n" + SEP
    + "MSG: geometry_msgs/Vector3\nfloat64 x\nfloat64 y\nfloat64 z\n" + SEP
    + "MSG: geometry_msgs/Quaternion\nfloat64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1\n")

SCHEMAS = {POINTCLOUD2: POINTCLOUD2_DEF, JOINTSTATE: JOINTSTATE_DEF, TFMESSAGE: TFMESSAGE_DEF,
           LAYERMARK: LAYERMARK_DEF}

JOINT_NAMES = tuple(f"joint_{i}" for i in range(1, 7))
CLOUD_FIELDS = ("x", "y", "z", "intensity")
FLOAT32 = 7
POINT_STEP = 16
MM_PER_M = 1000.0


def _cloud_points(xz_mm: np.ndarray, valid: np.ndarray, intensity: np.ndarray) -> np.ndarray:
    """``(n, 4)`` little-endian float32 ``x, y, z, intensity`` [m], NaN where invalid."""
    n = xz_mm.shape[0]
    pts = np.zeros((n, 4), dtype="<f4")
    pts[:, 0] = xz_mm[:, 0] / MM_PER_M
    pts[:, 2] = xz_mm[:, 1] / MM_PER_M
    pts[~valid, :3] = np.nan
    pts[:, 3] = intensity
    return pts


def cloud_msg(stamp_ns_: int, frame_id: str, pts: np.ndarray):
    """The ``rosbags`` PointCloud2 of ``(n, 4)`` float32 points (``_cloud_points``)."""
    n = pts.shape[0]
    field = msg_class("sensor_msgs/msg/PointField")
    fields = [field(name=name, offset=4 * i, datatype=FLOAT32, count=1)
              for i, name in enumerate(CLOUD_FIELDS)]
    return msg_class(POINTCLOUD2)(
        header=header(stamp_ns_, frame_id), height=1, width=n, fields=fields,
        is_bigendian=False, point_step=POINT_STEP, row_step=POINT_STEP * n,
        data=np.ascontiguousarray(pts).view(np.uint8).reshape(-1), is_dense=False)


@cache
def _cloud_template(frame_id: str) -> tuple[bytes, int]:
    """rosbags' PointCloud2 of no points in ``frame_id`` up to its data length, and the offset
    of ``width`` (then ``height``, ``width``, fields, ..., ``row_step``, data length)."""
    data = serialize(cloud_msg(0, frame_id, np.zeros((0, 4), "<f4")), POINTCLOUD2)
    end_of_frame = 4 + 8 + 4 + len(frame_id.encode()) + 1  # encapsulation, stamp, string
    width_at = end_of_frame + (-(end_of_frame - 4)) % 4 + 4
    return data[:-1], width_at  # less is_dense, which follows the data


def encode_cloud(stamp_ns_: int, frame_id: str, xz_mm: np.ndarray, valid: np.ndarray,
                 intensity: np.ndarray) -> bytes:
    """PointCloud2 of one profile: ``xz_mm (n, 2)`` [mm] written in metres, NaN where invalid
    (rosbags' bytes, from a per-frame template: the hot path)."""
    pts = _cloud_points(xz_mm, valid, intensity)
    n = pts.shape[0]
    template, width_at = _cloud_template(frame_id)
    buf = bytearray(template)
    struct.pack_into("<iI", buf, 4, *split_ns(stamp_ns_))
    struct.pack_into("<I", buf, width_at, n)
    struct.pack_into("<II", buf, len(buf) - 8, POINT_STEP * n, POINT_STEP * n)  # row, data
    return b"".join((buf, pts.tobytes(), b"\x00"))  # is_dense = False: NaN marks invalid


def decode_cloud(data: bytes) -> tuple[int, str, np.ndarray, np.ndarray, np.ndarray]:
    """Inverse of :func:`encode_cloud`: ``(stamp_ns, frame_id, xz_mm, valid, intensity)``."""
    m = deserialize(data, POINTCLOUD2)
    offsets = {f.name: (f.offset, f.datatype, f.count) for f in m.fields}
    for name in ("x", "z", "intensity"):
        if offsets.get(name, (0, 0, 0))[1:] != (FLOAT32, 1):
            raise CdrError(f"PointCloud2 field {name!r} missing or not FLOAT32")
    if m.is_bigendian:
        raise CdrError("big-endian PointCloud2 not supported")
    n, step = m.height * m.width, m.point_step
    if len(m.data) < n * step:
        raise CdrError("PointCloud2 data shorter than height * width * point_step")
    rec = m.data[:n * step].reshape(n, step)

    def column(name: str) -> np.ndarray:
        off = offsets[name][0]
        return rec[:, off:off + 4].copy().view("<f4")[:, 0]

    x, z = column("x"), column("z")
    valid = np.isfinite(x) & np.isfinite(z)
    xz_mm = np.column_stack([x.astype(np.float64), z.astype(np.float64)]) * MM_PER_M
    xz_mm[~valid] = np.nan
    return (stamp_ns(m.header.stamp), m.header.frame_id, xz_mm, valid,
            column("intensity").astype(np.float32))


def _joint_state_msg(stamp_ns_: int, joints_rad) -> object:
    return msg_class(JOINTSTATE)(
        header=header(stamp_ns_, ""), name=list(JOINT_NAMES),
        position=np.asarray(joints_rad, dtype=np.float64), velocity=np.zeros(0),
        effort=np.zeros(0))


@cache
def _joint_template() -> tuple[bytes, int]:
    """rosbags' JointState of the six joints, and the offset of its positions."""
    probe = np.arange(1.0, len(JOINT_NAMES) + 1.0) / 7.0
    data = serialize(_joint_state_msg(0, probe), JOINTSTATE)
    return data, data.index(probe.astype("<f8").tobytes())


def encode_joint_state(stamp_ns_: int, joints_rad: np.ndarray) -> bytes:
    """JointState with ``joint_1..joint_6`` positions [rad] (empty velocity and effort;
    rosbags' bytes, from a template: the hot path)."""
    q = np.asarray(joints_rad, dtype="<f8")
    if q.shape != (len(JOINT_NAMES),):
        return serialize(_joint_state_msg(stamp_ns_, q), JOINTSTATE)
    template, at = _joint_template()
    buf = bytearray(template)
    struct.pack_into("<iI", buf, 4, *split_ns(stamp_ns_))
    buf[at:at + q.nbytes] = q.tobytes()
    return bytes(buf)


def decode_joint_state(data: bytes) -> tuple[int, list[str], np.ndarray]:
    """``(stamp_ns, names, position_rad)`` of a JointState."""
    m = deserialize(data, JOINTSTATE)
    return stamp_ns(m.header.stamp), list(m.name), np.array(m.position, dtype=np.float64)


def quat_xyzw(R: np.ndarray) -> tuple[float, float, float, float]:
    """Unit quaternion ``(x, y, z, w)`` with ``w >= 0`` of a rotation matrix (Shepperd)."""
    (m00, m01, m02), (m10, m11, m12), (m20, m21, m22) = np.asarray(R)[:3, :3].tolist()
    tr = m00 + m11 + m22
    if tr > max(m00, m11, m22):
        s = 2.0 * math.sqrt(1.0 + tr)
        q = ((m21 - m12) / s, (m02 - m20) / s, (m10 - m01) / s, 0.25 * s)
    elif m00 >= m11 and m00 >= m22:
        s = 2.0 * math.sqrt(1.0 + m00 - m11 - m22)
        q = (0.25 * s, (m01 + m10) / s, (m02 + m20) / s, (m21 - m12) / s)
    elif m11 >= m22:
        s = 2.0 * math.sqrt(1.0 + m11 - m00 - m22)
        q = ((m01 + m10) / s, 0.25 * s, (m12 + m21) / s, (m02 - m20) / s)
    else:
        s = 2.0 * math.sqrt(1.0 + m22 - m00 - m11)
        q = ((m02 + m20) / s, (m12 + m21) / s, 0.25 * s, (m10 - m01) / s)
    n = math.sqrt(sum(v * v for v in q))
    sign = 1.0 if q[3] >= 0 else -1.0
    return tuple(sign * v / n for v in q)


def encode_tf(transforms: list[tuple[int, str, str, np.ndarray]]) -> bytes:
    """TFMessage of ``(stamp_ns, parent, child, T_parent_child)`` (translation mm -> m)."""
    vector, quat = msg_class("geometry_msgs/msg/Vector3"), msg_class("geometry_msgs/msg/Quaternion")
    stamped, transform = (msg_class("geometry_msgs/msg/TransformStamped"),
                          msg_class("geometry_msgs/msg/Transform"))
    out = []
    for ns, parent, child, T in transforms:
        x_m, y_m, z_m = (np.asarray(T, dtype=np.float64)[:3, 3] / MM_PER_M).tolist()
        qx, qy, qz, qw = quat_xyzw(T)
        out.append(stamped(header=header(ns, parent), child_frame_id=child, transform=transform(
            translation=vector(x=x_m, y=y_m, z=z_m), rotation=quat(x=qx, y=qy, z=qz, w=qw))))
    return serialize(msg_class(TFMESSAGE)(transforms=out), TFMESSAGE)


def matrix_from_quat_xyzw(x: float, y: float, z: float, w: float) -> np.ndarray:
    """(3, 3) rotation of a quaternion ``(x, y, z, w)`` (normalised first)."""
    n = math.sqrt(x * x + y * y + z * z + w * w)
    if not n > 0 or not math.isfinite(n):
        raise CdrError(f"invalid quaternion {(x, y, z, w)}")
    x, y, z, w = x / n, y / n, z / n, w / n
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def decode_tf(data: bytes) -> list[tuple[int, str, str, np.ndarray]]:
    """Inverse of :func:`encode_tf`: ``(stamp_ns, parent, child, T_parent_child [mm])``."""
    out = []
    for ts in deserialize(data, TFMESSAGE).transforms:
        q, t = ts.transform.rotation, ts.transform.translation
        T = np.eye(4)
        T[:3, :3] = matrix_from_quat_xyzw(q.x, q.y, q.z, q.w)
        T[:3, 3] = np.array([t.x, t.y, t.z]) * MM_PER_M
        out.append((stamp_ns(ts.header.stamp), ts.header.frame_id, ts.child_frame_id, T))
    return out


def encode_layer_mark(stamp_ns_: int, layer: int) -> bytes:
    return serialize(msg_class(LAYERMARK)(stamp=ros_time(stamp_ns_), layer=int(layer)), LAYERMARK)


def decode_layer_mark(data: bytes) -> tuple[int, int]:
    m = deserialize(data, LAYERMARK)
    return stamp_ns(m.stamp), m.layer
