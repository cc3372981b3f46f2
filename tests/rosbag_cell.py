"""rosbag2 recordings of an analytic cell, written with ``rosbags``' own writer (independent of
the project's recording writer): a dome on a plate scanned by three line profilers whose poses
are known (:mod:`test_monitor_scene`), the robot moving the plate under them.

:func:`write_bag` writes the stream either in the pipeline's own names (one ``B -> F`` edge on
``/tf``) or in a cell's own names with a six-link robot chain ``base_link -> link_1 .. link_6``
on ``/tf`` and ``link_6 -> tool0`` on ``/tf_static``; sensors hang off a static ``cell`` frame.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from scipy.spatial.transform import Rotation
from test_monitor_scene import Scene, make_calibration, raster_lines, raster_run

from dm2.core.frames import invert, make_T
from dm2.core.messages import Profile, RobotState
from dm2.io.ros_messages import LAYERMARK, LAYERMARK_DEF

TS = get_typestore(Stores.ROS2_HUMBLE)
TS.register(get_types_from_msg(LAYERMARK_DEF, LAYERMARK))
DOME = Scene(spheres=[((60.0, 60.0, -20.0), 35.0)])  # a cap 15 mm high, 57 mm across
FOREIGN_SENSORS = {"S1": "scanner_left", "S2": "scanner_rear", "S3": "scanner_right"}
FOREIGN_TOPICS = {"S1": "/scanners/left/points", "S2": "/scanners/rear/points",
                  "S3": "/scanners/right/points"}
FOREIGN_MAP = """\
[topics]
profiles = { S1 = "/scanners/left/points", S2 = "/scanners/rear/points", S3 = "/scanners/right/points" }
tf = "/tf"
tf_static = "/tf_static"
joint_states = "/joint_states"
[frames]
base = "base_link"
flange = "tool0"
work_object = "plate"
nozzle = "nozzle_exit"
sensors = { S1 = "scanner_left", S2 = "scanner_rear", S3 = "scanner_right" }
"""  # noqa: E501
T_L6_TOOL0 = make_T(Rotation.from_euler("z", 30, degrees=True).as_matrix(), [0.0, 0.0, 85.0])
T_B_CELL = make_T(Rotation.from_euler("xz", [3, -20], degrees=True).as_matrix(),
                  [900.0, 50.0, 400.0])


def dome_stream(t0_s: float = 1.0, step_mm: float = 0.75, n_rays: int = 160):
    """``(calibration, messages in stamp order, true hits (n, 3) in O)`` of a raster over
    the dome. The raster lines lie between voxel planes (y = 48.2, ...): on a line exactly at
    a multiple of the voxel size, S1's plate hits (all at the spot's y) would sit exactly on a
    voxel boundary, which only exact synthetic poses produce."""
    cal = make_calibration()
    lines = raster_lines((30.0, 90.0), [48.2, 60.2, 72.2])
    msgs, hits = raster_run(DOME, cal, lines, step_mm=step_mm, dt_s=0.05, noise_mm=0.03, seed=5,
                            t0_s=t0_s, n_rays=n_rays)
    return cal, msgs, hits


def _time(stamp_s: float):
    ns = round(stamp_s * 1e9)
    return TS.types["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9)


def _tf(stamp_s: float, parent: str, child: str, T: np.ndarray):
    t = TS.types
    q = Rotation.from_matrix(T[:3, :3]).as_quat()
    return t["geometry_msgs/msg/TransformStamped"](
        header=t["std_msgs/msg/Header"](stamp=_time(stamp_s), frame_id=parent),
        child_frame_id=child,
        transform=t["geometry_msgs/msg/Transform"](
            translation=t["geometry_msgs/msg/Vector3"](*(T[:3, 3] / 1000.0)),
            rotation=t["geometry_msgs/msg/Quaternion"](*q)))


def _links(stamp_s: float, T_B_F: np.ndarray) -> list[np.ndarray]:
    """Six dynamic link transforms whose product is ``T_B_F @ inv(T_L6_TOOL0)``."""
    Ls = []
    for k in range(5):
        ang = 0.3 * np.sin(0.7 * stamp_s + k) + 0.1 * k
        axis = "zyyxy"[k]
        Ls.append(make_T(Rotation.from_euler(axis, ang).as_matrix(), [0.0, 20.0 * k, 150.0]))
    prod = np.eye(4)
    for L in Ls:
        prod = prod @ L
    Ls.append(invert(prod) @ T_B_F @ invert(T_L6_TOOL0))
    return Ls


def _cloud(p: Profile, frame: str, float64: bool, organised: bool, zero_invalid: bool):
    t = TS.types
    n = p.n_points
    xyz = np.zeros((n, 3))
    xyz[:, 0], xyz[:, 2] = p.xz_S[:, 0] / 1000.0, p.xz_S[:, 1] / 1000.0
    xyz[~p.valid] = 0.0 if zero_invalid else np.nan
    if float64:  # x, y, z FLOAT64, no intensity
        data = xyz.astype("<f8").tobytes()
        fields = [t["sensor_msgs/msg/PointField"](name=c, offset=8 * i, datatype=8, count=1)
                  for i, c in enumerate("xyz")]
        step = 24
    else:
        pts = np.zeros((n, 4), "<f4")
        pts[:, :3], pts[:, 3] = xyz, p.intensity
        data = pts.tobytes()
        fields = [t["sensor_msgs/msg/PointField"](name=c, offset=4 * i, datatype=7, count=1)
                  for i, c in enumerate(("x", "y", "z", "intensity"))]
        step = 16
    height, width = (n, 1) if organised else (1, n)
    return t["sensor_msgs/msg/PointCloud2"](
        header=t["std_msgs/msg/Header"](stamp=_time(p.stamp_s), frame_id=frame),
        height=height, width=width, fields=fields, is_bigendian=False, point_step=step,
        row_step=step * width, data=np.frombuffer(data, np.uint8), is_dense=zero_invalid)


def _messages(cal, msgs, foreign: bool, float64: bool, cloud_frames=None, marks=()):
    """``(topic, msgtype, stamp_ns, message)`` of the whole recording."""
    t = TS.types
    out = []
    sensors = FOREIGN_SENSORS if foreign else {s: s for s in cal.T_B_S}
    cloud_frames = cloud_frames or sensors
    if foreign:
        statics = [_tf(0.0, "link_6", "tool0", T_L6_TOOL0),
                   _tf(0.0, "base_link", "cell", T_B_CELL),
                   _tf(0.0, "cell", "nozzle_exit", invert(T_B_CELL) @ cal.T_B_N),
                   _tf(0.0, "tool0", "plate", cal.T_F_O)]
        statics += [_tf(0.0, "cell", sensors[s], invert(T_B_CELL) @ T) for s, T in
                    cal.T_B_S.items()]
    else:
        statics = [_tf(0.0, "B", "N", cal.T_B_N), _tf(0.0, "F", "O", cal.T_F_O)]
        statics += [_tf(0.0, "B", s, T) for s, T in cal.T_B_S.items()]
    out.append(("/tf_static", "tf2_msgs/msg/TFMessage", 0, t["tf2_msgs/msg/TFMessage"](statics)))
    topics = FOREIGN_TOPICS if foreign else {s: f"/scan/{s}" for s in cal.T_B_S}
    for stamp_s, layer in marks:
        out.append(("/dm2/layer", LAYERMARK, round(stamp_s * 1e9),
                    t[LAYERMARK](stamp=_time(stamp_s), layer=layer)))
    for m in msgs:
        ns = round(m.stamp_s * 1e9)
        if isinstance(m, RobotState):
            if foreign:
                frames = ["base_link"] + [f"link_{k}" for k in range(1, 7)]
                links = _links(m.stamp_s, m.T_B_F)
                tfs = [_tf(m.stamp_s, frames[k], frames[k + 1], links[k]) for k in range(6)]
                # a driver publishing the chain in two messages
                out.append(("/tf", "tf2_msgs/msg/TFMessage", ns,
                            t["tf2_msgs/msg/TFMessage"](tfs[:3])))
                out.append(("/tf", "tf2_msgs/msg/TFMessage", ns,
                            t["tf2_msgs/msg/TFMessage"](tfs[3:])))
            else:
                out.append(("/tf", "tf2_msgs/msg/TFMessage", ns,
                            t["tf2_msgs/msg/TFMessage"]([_tf(m.stamp_s, "B", "F", m.T_B_F)])))
            js = t["sensor_msgs/msg/JointState"](
                header=t["std_msgs/msg/Header"](stamp=_time(m.stamp_s), frame_id=""),
                name=[f"joint_{k}" for k in range(1, 7)], position=np.asarray(m.joints_rad),
                velocity=np.zeros(0), effort=np.zeros(0))
            out.append(("/joint_states", "sensor_msgs/msg/JointState", ns, js))
        elif isinstance(m, Profile):
            out.append((topics[m.sensor_id], "sensor_msgs/msg/PointCloud2", ns,
                        _cloud(m, cloud_frames[m.sensor_id], float64, organised=foreign,
                               zero_invalid=foreign)))
    return out


def write_bag(path: Path, cal, msgs, *, foreign: bool = False, float64: bool = False,
              storage: str = "mcap", split: bool = False, duplicate: int = 0,
              cloud_frames=None, marks=(), tf_hole_s=None) -> Path:
    """Write a rosbag2 folder at ``path`` (``storage`` "mcap" or "sqlite3"); ``split``: two
    files split half-way in time; ``duplicate``: record that many profiles twice;
    ``cloud_frames``: sensor -> the frame_id its clouds carry (default: its own frame);
    ``marks``: ``(stamp_s, layer)`` layer marks on ``/dm2/layer``; ``tf_hole_s``: ``(t0, t1)``,
    no ``/tf`` message in between (a driver that stalled)."""
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    rows = _messages(cal, msgs, foreign, float64, cloud_frames, marks)
    if tf_hole_s is not None:
        lo, hi = (round(t * 1e9) for t in tf_hole_s)
        rows = [r for r in rows if not (r[0] == "/tf" and lo < r[2] < hi)]
    clouds = [i for i, r in enumerate(rows) if r[1] == "sensor_msgs/msg/PointCloud2"]
    for i in clouds[10:10 + duplicate]:
        rows.append(rows[i])
    rows.sort(key=lambda r: r[2])
    parts = [rows[: len(rows) // 2], rows[len(rows) // 2:]] if split else [rows]
    if split:  # /tf_static is latched: a split file starts with it again
        parts[1].insert(0, rows[0])
    bags = [path] if not split else [path.with_name(path.name + f"_{k}") for k in range(2)]
    for bag, part in zip(bags, parts, strict=True):
        with Writer(bag, version=9, storage_plugin=plugin) as w:
            conns = {}
            for topic, msgtype, _ns, _m in part:
                if topic not in conns:
                    conns[topic] = w.add_connection(topic, msgtype, typestore=TS)
            for topic, msgtype, ns, m in part:
                w.write(conns[topic], ns, TS.serialize_cdr(m, msgtype))
    if split:
        _merge_split(path, bags)
    return path


def _merge_split(path: Path, bags: list[Path]) -> None:
    """Join two bags into one split bag folder (as ``ros2 bag record --max-bag-duration``
    leaves it: one metadata.yaml listing both files)."""
    from ruamel.yaml import YAML

    yaml = YAML(typ="safe")
    metas = [yaml.load((b / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
             for b in bags]
    path.mkdir()
    names = []
    for k, (bag, meta) in enumerate(zip(bags, metas, strict=True)):
        src = bag / meta["relative_file_paths"][0]
        name = f"{path.name}_{k}{src.suffix}"
        shutil.move(src, path / name)
        names.append(name)
        shutil.rmtree(bag)
    m0, m1 = metas
    counts = {t["topic_metadata"]["name"]: t for t in m0["topics_with_message_count"]}
    for t in m1["topics_with_message_count"]:
        name = t["topic_metadata"]["name"]
        if name in counts:
            counts[name]["message_count"] += t["message_count"]
        else:
            counts[name] = t
    files = []
    for name, meta in zip(names, metas, strict=True):
        f = dict(meta["files"][0])
        f["path"] = name
        files.append(f)
    start = min(m["starting_time"]["nanoseconds_since_epoch"] for m in metas)
    end = max(m["starting_time"]["nanoseconds_since_epoch"] + m["duration"]["nanoseconds"]
              for m in metas)
    m0.update(relative_file_paths=names, files=files,
              message_count=m0["message_count"] + m1["message_count"],
              topics_with_message_count=list(counts.values()),
              duration={"nanoseconds": end - start},
              starting_time={"nanoseconds_since_epoch": start})
    out = YAML()
    with open(path / "metadata.yaml", "w") as f:
        out.dump({"rosbag2_bagfile_information": m0}, f)


def storage_file(bag: Path) -> Path:
    """The one storage file of an unsplit bag folder (to open it on its own)."""
    (f,) = [p for p in bag.iterdir() if p.suffix in (".mcap", ".db3")]
    return f


def write_mcap_ros2(path: Path, cal, msgs) -> Path:
    """The stream as one MCAP file written by ``mcap-ros2-support`` in the pipeline's names,
    every message record with ``sequence = 0`` (as rosbag2's MCAP storage writes them)."""
    from mcap_ros2.writer import Writer as McapWriter

    from dm2.io import ros_messages as ros

    def stamp(ns):
        return {"sec": ns // 10**9, "nanosec": ns % 10**9}

    def tf_msg(tfs):
        return {"transforms": [
            {"header": {"stamp": stamp(ns), "frame_id": a}, "child_frame_id": b,
             "transform": {"translation": dict(zip("xyz", (T[:3, 3] / 1000).tolist(),
                                                   strict=True)),
                           "rotation": dict(zip("xyzw", Rotation.from_matrix(
                               T[:3, :3]).as_quat().tolist(), strict=True))}}
            for ns, a, b, T in tfs]}

    with open(path, "wb") as f:
        w = McapWriter(f)
        schema = {n: w.register_msgdef(n, d) for n, d in ros.SCHEMAS.items()}
        statics = [(0, "B", "N", cal.T_B_N), (0, "F", "O", cal.T_F_O)]
        statics += [(0, "B", s, T) for s, T in cal.T_B_S.items()]
        w.write_message("/tf_static", schema[ros.TFMESSAGE], tf_msg(statics), log_time=0,
                        publish_time=0, sequence=0)
        for m in msgs:
            ns = round(m.stamp_s * 1e9)
            if isinstance(m, RobotState):
                w.write_message("/tf", schema[ros.TFMESSAGE], tf_msg([(ns, "B", "F", m.T_B_F)]),
                                log_time=ns, publish_time=ns, sequence=0)
                continue
            pts = np.zeros((m.n_points, 4), "<f4")
            pts[:, 0], pts[:, 2] = m.xz_S[:, 0] / 1000, m.xz_S[:, 1] / 1000
            pts[:, 3] = m.intensity
            cloud = {"header": {"stamp": stamp(ns), "frame_id": m.sensor_id}, "height": 1,
                     "width": m.n_points,
                     "fields": [{"name": c, "offset": 4 * i, "datatype": 7, "count": 1}
                                for i, c in enumerate(("x", "y", "z", "intensity"))],
                     "is_bigendian": False, "point_step": 16, "row_step": 16 * m.n_points,
                     "data": pts.tobytes(), "is_dense": False}
            w.write_message(f"/scan/{m.sensor_id}", schema[ros.POINTCLOUD2], cloud, log_time=ns,
                            publish_time=ns, sequence=0)
        w.finish()
    return path
