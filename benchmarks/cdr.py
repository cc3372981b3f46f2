"""CDR speed: the recording's message encoders and decoders against ``rosbags``' serializer.

For each ROS 2 message type a dm2 recording holds (``sensor_msgs/PointCloud2`` profiles,
``sensor_msgs/JointState``, ``tf2_msgs/TFMessage`` with one dynamic and with five static
transforms, ``dm2_msgs/LayerMark``), times in one run:

- ours: :mod:`dm2.io.ros_messages`' ``encode_*`` / ``decode_*`` (whatever path it takes);
- rosbags: the same conversion through ``rosbags``' message classes and ``serialize_cdr`` /
  ``deserialize_cdr`` alone (numpy in, the same tuple out),

and prints the median over ``--runs`` runs of µs per message and the ratio ours / rosbags
(below 1: ours is faster). Both paths are first checked to give identical bytes.

    .venv/bin/python benchmarks/cdr.py [--points 1280] [--runs 7] [--repeat 2000]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).parent.resolve()]
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from dm2.io import ros_messages as ros  # noqa: E402


def _typestore():
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    ts.register(get_types_from_msg(ros.LAYERMARK_DEF, ros.LAYERMARK))
    return ts


TS = _typestore()
T = TS.types
Time, Header = T["builtin_interfaces/msg/Time"], T["std_msgs/msg/Header"]


def _time(ns: int):
    sec, nsec = divmod(int(ns), 1_000_000_000)
    return Time(sec=sec, nanosec=nsec)


def rb_encode_cloud(ns, frame_id, xz_mm, valid, intensity) -> bytes:
    n = xz_mm.shape[0]
    pts = np.zeros((n, 4), dtype="<f4")
    pts[:, 0], pts[:, 2] = xz_mm[:, 0] / 1000.0, xz_mm[:, 1] / 1000.0
    pts[~valid, :3] = np.nan
    pts[:, 3] = intensity
    PF = T["sensor_msgs/msg/PointField"]
    fields = [PF(name=c, offset=4 * i, datatype=7, count=1)
              for i, c in enumerate(("x", "y", "z", "intensity"))]
    msg = T[ros.POINTCLOUD2](
        header=Header(stamp=_time(ns), frame_id=frame_id), height=1, width=n, fields=fields,
        is_bigendian=False, point_step=16, row_step=16 * n,
        data=pts.view(np.uint8).reshape(-1), is_dense=False)
    return bytes(TS.serialize_cdr(msg, ros.POINTCLOUD2))


def rb_decode_cloud(data: bytes):
    m = TS.deserialize_cdr(data, ros.POINTCLOUD2)
    n = m.height * m.width
    off = {f.name: f.offset for f in m.fields}
    rec = m.data[:n * m.point_step].reshape(n, m.point_step)

    def column(name):
        return rec[:, off[name]:off[name] + 4].copy().view("<f4")[:, 0]

    x, z = column("x"), column("z")
    valid = np.isfinite(x) & np.isfinite(z)
    xz_mm = np.column_stack([x.astype(np.float64), z.astype(np.float64)]) * 1000.0
    xz_mm[~valid] = np.nan
    stamp = m.header.stamp
    return (stamp.sec * 10**9 + stamp.nanosec, m.header.frame_id, xz_mm, valid,
            column("intensity").astype(np.float32))


def rb_encode_joint_state(ns, joints_rad) -> bytes:
    msg = T[ros.JOINTSTATE](
        header=Header(stamp=_time(ns), frame_id=""), name=list(ros.JOINT_NAMES),
        position=np.asarray(joints_rad, np.float64), velocity=np.zeros(0), effort=np.zeros(0))
    return bytes(TS.serialize_cdr(msg, ros.JOINTSTATE))


def rb_decode_joint_state(data: bytes):
    m = TS.deserialize_cdr(data, ros.JOINTSTATE)
    return m.header.stamp.sec * 10**9 + m.header.stamp.nanosec, m.name, m.position


def rb_encode_tf(transforms) -> bytes:
    V, Q = T["geometry_msgs/msg/Vector3"], T["geometry_msgs/msg/Quaternion"]
    out = []
    for ns, parent, child, M in transforms:
        t = (np.asarray(M, np.float64)[:3, 3] / 1000.0).tolist()
        x, y, z, w = ros.quat_xyzw(M)
        out.append(T["geometry_msgs/msg/TransformStamped"](
            header=Header(stamp=_time(ns), frame_id=parent), child_frame_id=child,
            transform=T["geometry_msgs/msg/Transform"](
                translation=V(x=t[0], y=t[1], z=t[2]), rotation=Q(x=x, y=y, z=z, w=w))))
    return bytes(TS.serialize_cdr(T[ros.TFMESSAGE](transforms=out), ros.TFMESSAGE))


def rb_decode_tf(data: bytes):
    out = []
    for ts in TS.deserialize_cdr(data, ros.TFMESSAGE).transforms:
        q, t = ts.transform.rotation, ts.transform.translation
        M = np.eye(4)
        M[:3, :3] = ros.matrix_from_quat_xyzw(q.x, q.y, q.z, q.w)
        M[:3, 3] = np.array([t.x, t.y, t.z]) * 1000.0
        out.append((ts.header.stamp.sec * 10**9 + ts.header.stamp.nanosec,
                    ts.header.frame_id, ts.child_frame_id, M))
    return out


def rb_encode_layer_mark(ns, layer) -> bytes:
    return bytes(TS.serialize_cdr(T[ros.LAYERMARK](stamp=_time(ns), layer=layer), ros.LAYERMARK))


def rb_decode_layer_mark(data: bytes):
    m = TS.deserialize_cdr(data, ros.LAYERMARK)
    return m.stamp.sec * 10**9 + m.stamp.nanosec, m.layer


def _pose(rng) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    M = np.eye(4)
    M[:3, :3] = Rotation.from_rotvec(rng.normal(size=3)).as_matrix()
    M[:3, 3] = rng.uniform(-1500, 1500, 3)
    return M


def cases(n_points: int):
    """``(name, encoder args, ours encode, rosbags encode, ours decode, rosbags decode)``."""
    rng = np.random.default_rng(7)
    ns = 1_712_345_678_123_456_789
    xz = np.column_stack([rng.uniform(-40, 40, n_points), rng.uniform(80, 160, n_points)])
    valid = rng.random(n_points) > 0.05
    inten = rng.uniform(0, 1, n_points).astype(np.float32)
    tf1 = [(ns, "B", "F", _pose(rng))]
    tf5 = [(0, "B", f"S{i}", _pose(rng)) for i in range(5)]
    return [
        (f"PointCloud2 ({n_points} pts)", (ns, "S1", xz, valid, inten),
         ros.encode_cloud, rb_encode_cloud, ros.decode_cloud, rb_decode_cloud),
        ("JointState (6 joints)", (ns, rng.uniform(-3, 3, 6)), ros.encode_joint_state,
         rb_encode_joint_state, ros.decode_joint_state, rb_decode_joint_state),
        ("TFMessage (1 transform)", (tf1,), ros.encode_tf, rb_encode_tf, ros.decode_tf,
         rb_decode_tf),
        ("TFMessage (5 transforms)", (tf5,), ros.encode_tf, rb_encode_tf, ros.decode_tf,
         rb_decode_tf),
        ("LayerMark", (ns, 12), ros.encode_layer_mark, rb_encode_layer_mark,
         ros.decode_layer_mark, rb_decode_layer_mark),
    ]


def _us_per_call(fn, args, repeat: int) -> float:
    t = time.perf_counter()
    for _ in range(repeat):
        fn(*args)
    return (time.perf_counter() - t) / repeat * 1e6


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, default=1280, help="points per profile")
    ap.add_argument("--runs", type=int, default=7)
    ap.add_argument("--repeat", type=int, default=2000, help="messages per timed run")
    args = ap.parse_args()
    print(f"median of {args.runs} runs of {args.repeat} messages, µs/message")
    print(f"{'message':26s} {'op':6s} {'ours':>8s} {'rosbags':>8s} {'ratio':>6s}")
    for name, enc_args, enc, rb_enc, dec, rb_dec in cases(args.points):
        data = enc(*enc_args)
        if data != rb_enc(*enc_args):
            raise SystemExit(f"{name}: ours and rosbags encode different bytes")
        for op, ours, theirs, a in (("encode", enc, rb_enc, enc_args),
                                    ("decode", dec, rb_dec, (data,))):
            t_ours, t_rb = [], []
            for _ in range(args.runs):  # interleaved, so both see the same machine load
                t_ours.append(_us_per_call(ours, a, args.repeat))
                t_rb.append(_us_per_call(theirs, a, args.repeat))
            mo, mr = statistics.median(t_ours), statistics.median(t_rb)
            print(f"{name:26s} {op:6s} {mo:8.2f} {mr:8.2f} {mo / mr:6.2f}")


if __name__ == "__main__":
    main()
