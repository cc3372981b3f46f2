"""ROS 2 message schemas and their CDR encoding for dm2 recordings.

Recordings use the standard ROS 2 types so that Foxglove and ROS 2 tools open them:

- ``sensor_msgs/msg/PointCloud2`` for profiles: ``height = 1``, ``width = n`` points, fields
  ``x, y, z, intensity`` (FLOAT32, little endian, ``point_step = 16``), coordinates in metres
  in the sensor frame (``y = 0``, the laser plane), invalid points written as NaN so the point
  count and validity survive (``is_dense = False``).
- ``sensor_msgs/msg/JointState`` for joints (``joint_1 .. joint_6``, radians).
- ``tf2_msgs/msg/TFMessage`` for ``/tf`` and ``/tf_static`` (translations in metres).
- ``dm2_msgs/msg/LayerMark`` (``builtin_interfaces/Time stamp``, ``int32 layer``).

The CDR (XCDR1, little endian) encoders and decoders here are written out by hand for these
fixed layouts (primitives in :mod:`dm2.io.cdr`): they are several times faster than the generic
dynamic encoder, and the tests check them against ``mcap_ros2``'s independent decoder.
"""

from __future__ import annotations

import math
import struct

import numpy as np

from dm2.io.cdr import CdrError, CdrReader, CdrWriter, split_ns

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

LAYERMARK = "dm2_msgs/msg/LayerMark"
LAYERMARK_DEF = "builtin_interfaces/Time stamp\nint32 layer\n"

SCHEMAS = {POINTCLOUD2: POINTCLOUD2_DEF, JOINTSTATE: JOINTSTATE_DEF, TFMESSAGE: TFMESSAGE_DEF,
           LAYERMARK: LAYERMARK_DEF}

JOINT_NAMES = tuple(f"joint_{i}" for i in range(1, 7))
CLOUD_FIELDS = ("x", "y", "z", "intensity")
FLOAT32 = 7
POINT_STEP = 16
MM_PER_M = 1000.0


def encode_cloud(stamp_ns: int, frame_id: str, xz_mm: np.ndarray, valid: np.ndarray,
                 intensity: np.ndarray) -> bytes:
    """PointCloud2 of one profile: ``xz_mm (n, 2)`` [mm] written in metres, NaN where invalid."""
    n = xz_mm.shape[0]
    pts = np.zeros((n, 4), dtype="<f4")
    pts[:, 0] = xz_mm[:, 0] / MM_PER_M
    pts[:, 2] = xz_mm[:, 1] / MM_PER_M
    pts[~valid, :3] = np.nan
    pts[:, 3] = intensity
    w = CdrWriter()
    w.header(stamp_ns, frame_id)
    w.u32(1)
    w.u32(n)
    w.u32(len(CLOUD_FIELDS))
    for i, name in enumerate(CLOUD_FIELDS):
        w.string(name)
        w.u32(4 * i)
        w.u8(FLOAT32)
        w.u32(1)
    w.u8(0)  # is_bigendian
    w.u32(POINT_STEP)
    w.u32(POINT_STEP * n)
    w.u32(POINT_STEP * n)
    w.buf += pts.tobytes()
    w.u8(0)  # is_dense: NaN marks invalid points
    return bytes(w.buf)


def decode_cloud(data: bytes) -> tuple[int, str, np.ndarray, np.ndarray, np.ndarray]:
    """Inverse of :func:`encode_cloud`: ``(stamp_ns, frame_id, xz_mm, valid, intensity)``."""
    r = CdrReader(data)
    stamp_ns = r.time_ns()
    frame_id = r.string()
    height, width = r.u32(), r.u32()
    offsets = {}
    for _ in range(r.u32()):
        name, offset, dtype, count = r.string(), r.u32(), r.u8(), r.u32()
        offsets[name] = (offset, dtype, count)
    big = r.u8()
    point_step, _row_step = r.u32(), r.u32()
    nbytes = r.u32()
    raw = r._take(nbytes)
    for name in ("x", "z", "intensity"):
        if offsets.get(name, (0, 0, 0))[1:] != (FLOAT32, 1):
            raise CdrError(f"PointCloud2 field {name!r} missing or not FLOAT32")
    if big:
        raise CdrError("big-endian PointCloud2 not supported")
    n = height * width
    if nbytes < n * point_step:
        raise CdrError("PointCloud2 data shorter than height * width * point_step")
    rec = np.frombuffer(raw, dtype=np.uint8)[:n * point_step].reshape(n, point_step)

    def column(name: str) -> np.ndarray:
        off = offsets[name][0]
        return rec[:, off:off + 4].copy().view("<f4")[:, 0]

    x, z = column("x"), column("z")
    valid = np.isfinite(x) & np.isfinite(z)
    xz_mm = np.column_stack([x.astype(np.float64), z.astype(np.float64)]) * MM_PER_M
    xz_mm[~valid] = np.nan
    return stamp_ns, frame_id, xz_mm, valid, column("intensity").astype(np.float32)


def _encode_joint_state_general(stamp_ns: int, joints_rad) -> bytes:
    w = CdrWriter()
    w.header(stamp_ns, "")
    w.u32(len(JOINT_NAMES))
    for name in JOINT_NAMES:
        w.string(name)
    w.u32(len(joints_rad))
    w.f64s([float(v) for v in joints_rad])
    w.u32(0)
    w.u32(0)
    return bytes(w.buf)


_JOINT_TEMPLATE = _encode_joint_state_general(0, [0.0] * 6)
_JOINT_POS_OFFSET = len(_JOINT_TEMPLATE) - 8 - 48  # then empty velocity and effort


def encode_joint_state(stamp_ns: int, joints_rad: np.ndarray) -> bytes:
    """JointState with ``joint_1..joint_6`` positions [rad] (fixed layout, from a template)."""
    if len(joints_rad) != 6:
        return _encode_joint_state_general(stamp_ns, joints_rad)
    buf = bytearray(_JOINT_TEMPLATE)
    struct.pack_into("<iI", buf, 4, *split_ns(stamp_ns))
    buf[_JOINT_POS_OFFSET:_JOINT_POS_OFFSET + 48] = np.asarray(joints_rad, "<f8").tobytes()
    return bytes(buf)


def decode_joint_state(data: bytes) -> tuple[int, list[str], np.ndarray]:
    """``(stamp_ns, names, position_rad)`` of a JointState."""
    r = CdrReader(data)
    stamp_ns = r.time_ns()
    r.string()
    names = [r.string() for _ in range(r.u32())]
    position = r.f64s(r.u32())
    return stamp_ns, names, position


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
    w = CdrWriter()
    w.u32(len(transforms))
    for stamp_ns, parent, child, T in transforms:
        w.header(stamp_ns, parent)
        w.string(child)
        t_m = (np.asarray(T, dtype=np.float64)[:3, 3] / MM_PER_M).tolist()
        w.f64s([*t_m, *quat_xyzw(T)])
    return bytes(w.buf)


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
    r = CdrReader(data)
    out = []
    for _ in range(r.u32()):
        stamp_ns = r.time_ns()
        parent, child = r.string(), r.string()
        v = r.f64s(7)
        T = np.eye(4)
        T[:3, :3] = matrix_from_quat_xyzw(*v[3:].tolist())
        T[:3, 3] = v[:3] * MM_PER_M
        out.append((stamp_ns, parent, child, T))
    return out


def encode_layer_mark(stamp_ns: int, layer: int) -> bytes:
    w = CdrWriter()
    w.time(stamp_ns)
    w.i32(layer)
    return bytes(w.buf)


def decode_layer_mark(data: bytes) -> tuple[int, int]:
    r = CdrReader(data)
    return r.time_ns(), r.i32()
