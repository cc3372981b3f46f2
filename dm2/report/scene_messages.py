"""A run's results as Foxglove messages (foxglove-sdk's own schemas), each on the run's clock.

Every function returns ``(stamp_s, topic, message)`` triples; :mod:`dm2.report.scene_mcap`
logs them to ``scene.mcap`` and :mod:`dm2.view.foxglove_live` to a live server. Lengths are in
metres in the scene (Foxglove's unit), in millimetres in the numbers a message carries by name
(``deviation_mm``, ``area_mm2``, ...). Frames: ``base`` (B), ``flange`` (F), ``plate`` (O),
``nozzle`` (N), ``S1``..``S3``; points and boxes are in ``plate``.
"""

from __future__ import annotations

import numpy as np
from foxglove import messages as fm

from dm2.core.frames import to_quat_abb

M_PER_MM = 1e-3
PLATE, BASE, FLANGE, NOZZLE = "plate", "base", "flange", "nozzle"

TOPIC_SURFACE = "/dm2/surface"
TOPIC_REFERENCE = "/dm2/reference"
TOPIC_TRACKS = "/dm2/tracks"
TOPIC_TRACK_STATS = "/dm2/track_stats"
TOPIC_ALARMS = "/dm2/alarms"
TOPIC_ALARM_MARKERS = "/dm2/alarm_markers"
TOPIC_TF = "/tf"
TOPIC_PROFILES = "/dm2/profiles"
TOPIC_FINDINGS = "/dm2/findings"

# the plot channel's JSON schema (dm2's own numbers, not a Foxglove schema)
TRACK_STATS_SCHEMA_NAME = "dm2.TrackStats"
TRACK_STATS_SCHEMA = {"type": "object", "properties": {
    "layer": {"type": "integer"}, "track_id": {"type": "integer"}, "kind": {"type": "string"},
    "area_mm2": {"type": "number"}, "height_mm": {"type": "number"},
    "max_deviation_mm": {"type": "number"}}}

KIND_RGBA = {"overbuild": (0.84, 0.19, 0.15, 0.5), "underbuild": (0.27, 0.46, 0.71, 0.5),
             "local_overbuild": (0.99, 0.68, 0.38, 0.4),
             "local_underbuild": (0.6, 0.44, 0.67, 0.4)}
_F32, _U8 = fm.PackedElementFieldNumericType.Float32, fm.PackedElementFieldNumericType.Uint8
_CLOUD_DTYPE = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"),
                         ("green", "u1"), ("blue", "u1"), ("alpha", "u1"),
                         ("deviation_mm", "<f4")])


def stamp(stamp_s: float) -> fm.Timestamp:
    """The run clock's seconds as a Foxglove timestamp (negative stamps clamp to 0)."""
    ns = max(int(round(float(stamp_s) * 1e9)), 0)
    return fm.Timestamp(sec=ns // 1_000_000_000, nsec=ns % 1_000_000_000)


def _pose(xyz_mm=(0.0, 0.0, 0.0)) -> fm.Pose:
    x, y, z = (float(v) * M_PER_MM for v in xyz_mm)
    return fm.Pose(position=fm.Vector3(x=x, y=y, z=z),
                   orientation=fm.Quaternion(x=0.0, y=0.0, z=0.0, w=1.0))


def point_cloud(stamp_s: float, points_O_mm: np.ndarray, rgb: np.ndarray,
                deviation_mm: np.ndarray | None = None) -> fm.PointCloud:
    """Points (n, 3) [mm] in ``plate`` with colours (n, 3) uint8 and a ``deviation_mm`` field
    (NaN where none)."""
    n = len(points_O_mm)
    rec = np.zeros(n, dtype=_CLOUD_DTYPE)
    pts = np.asarray(points_O_mm, dtype=np.float64) * M_PER_MM
    rec["x"], rec["y"], rec["z"] = pts[:, 0], pts[:, 1], pts[:, 2]
    rec["red"], rec["green"], rec["blue"] = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    rec["alpha"] = 255
    rec["deviation_mm"] = np.nan if deviation_mm is None else deviation_mm
    fields = [fm.PackedElementField(name=name, offset=_CLOUD_DTYPE.fields[name][1],
                                    type=_F32 if _CLOUD_DTYPE[name].kind == "f" else _U8)
              for name in _CLOUD_DTYPE.names]
    return fm.PointCloud(timestamp=stamp(stamp_s), frame_id=PLATE, pose=_pose(),
                         point_stride=_CLOUD_DTYPE.itemsize, fields=fields,
                         data=rec.tobytes())


def layer_messages(result, limit_mm: float = 1.0) -> list:
    """One analysed layer: its fused surface coloured by signed deviation, the reference
    beneath it (the closest reference point of each vertex, grey), its tracks as labelled
    boxes (the scene replaced: a track lives over the layers it was seen) and one plot row
    per track. A region no track has confirmed (yet) is not shown."""
    from dm2.report.meshes import deviation_colours

    dev = result.deviation
    t = float(dev.stamp_s)
    rgb = deviation_colours(dev.signed_distance_mm, dev.class_code, limit_mm)
    grey = np.full((dev.n_vertices, 3), 160, np.uint8)
    out = [(t, TOPIC_SURFACE, point_cloud(t, dev.vertices_O, rgb, dev.signed_distance_mm)),
           (t, TOPIC_REFERENCE, point_cloud(t, dev.foot_O, grey))]
    entities, rows = [], []
    for region, tid in zip(result.regions, result.track_ids, strict=True):
        if tid is None:  # not (yet) confirmed as a track: not one of the report's tracks
            continue
        entities.append(track_entity(t, int(tid), result.layer, region))
        rows.append((t, TOPIC_TRACK_STATS, {
            "layer": int(result.layer), "track_id": int(tid), "kind": region.kind,
            "area_mm2": float(region.area_mm2), "height_mm": float(region.height_mm),
            "max_deviation_mm": float(region.max_deviation_mm)}))
    update = fm.SceneUpdate(
        deletions=[fm.SceneEntityDeletion(timestamp=stamp(t),
                                          type=fm.SceneEntityDeletionType.All, id="")],
        entities=entities)
    return [*out, (t, TOPIC_TRACKS, update), *rows]


def track_entity(t: float, track_id: int, layer: int, region) -> fm.SceneEntity:
    """A track's region in one layer: its box and a label; metadata id, kind, layer, area
    [mm^2] and peak (signed deviation of largest magnitude) [mm]."""
    lo, hi = np.asarray(region.bbox_min_O, float), np.asarray(region.bbox_max_O, float)
    size = np.maximum(hi - lo, 0.1) * M_PER_MM
    rgba = KIND_RGBA.get(region.kind, (0.5, 0.5, 0.5, 0.5))
    label = (f"#{track_id} {region.kind} {region.area_mm2:.0f} mm² "
             f"{region.max_deviation_mm:+.2f} mm")
    meta = {"id": str(track_id), "kind": region.kind, "layer": str(layer),
            "area_mm2": f"{region.area_mm2:.6g}", "peak_mm": f"{region.max_deviation_mm:.6g}"}
    return fm.SceneEntity(
        timestamp=stamp(t), frame_id=PLATE, id=f"track-{track_id}",
        metadata=[fm.KeyValuePair(key=k, value=v) for k, v in meta.items()],
        cubes=[fm.CubePrimitive(pose=_pose((lo + hi) / 2.0),
                                size=fm.Vector3(x=size[0], y=size[1], z=size[2]),
                                color=fm.Color(r=rgba[0], g=rgba[1], b=rgba[2], a=rgba[3]))],
        texts=[fm.TextPrimitive(pose=_pose((lo + hi) / 2.0 + [0.0, 0.0, hi[2] - lo[2] + 2.0]),
                                billboard=True, font_size=14.0, scale_invariant=True,
                                color=fm.Color(r=1.0, g=1.0, b=1.0, a=1.0), text=label)])


def alarm_messages(k: int, alarm: dict, z_mm: float) -> list:
    """A real-time alarm (report.json ``realtime.alarms`` entry): a warning log and a marker
    (a sphere at its centroid, at the height ``z_mm`` the part had reached)."""
    t = float(alarm["stamp_s"])
    x, y = alarm["centroid_xy_O_mm"][:2]
    text = (f"real-time alarm {k}: {alarm['kind']} at ({x:.1f}, {y:.1f}) mm, "
            f"{alarm['area_mm2']:.0f} mm², {alarm.get('delay_s', 0.0):.2f} s after first flag")
    log = fm.Log(timestamp=stamp(t), level=fm.LogLevel.Warning, message=text,
                 name="dm2.realtime", file="", line=0)
    d = 4.0 * M_PER_MM
    marker = fm.SceneEntity(
        timestamp=stamp(t), frame_id=PLATE, id=f"alarm-{k}",
        metadata=[fm.KeyValuePair(key="kind", value=str(alarm["kind"])),
                  fm.KeyValuePair(key="area_mm2", value=f"{alarm['area_mm2']:.6g}")],
        spheres=[fm.SpherePrimitive(pose=_pose((x, y, z_mm)),
                                    size=fm.Vector3(x=d, y=d, z=d),
                                    color=fm.Color(r=1.0, g=0.1, b=0.1, a=0.9))])
    return [(t, TOPIC_ALARMS, log), (t, TOPIC_ALARM_MARKERS, fm.SceneUpdate(entities=[marker]))]


def transform(t: float, parent: str, child: str, T_parent_child: np.ndarray
              ) -> fm.FrameTransform:
    trans, q = to_quat_abb(np.asarray(T_parent_child, dtype=np.float64))
    tx, ty, tz = (float(v) * M_PER_MM for v in trans)
    return fm.FrameTransform(timestamp=stamp(t), parent_frame_id=parent, child_frame_id=child,
                             translation=fm.Vector3(x=tx, y=ty, z=tz),
                             rotation=fm.Quaternion(w=float(q[0]), x=float(q[1]),
                                                    y=float(q[2]), z=float(q[3])))


def frame_messages(t: float, calibration, T_B_F: np.ndarray | None) -> tuple:
    """The frames at ``t``: base->flange (the robot pose, when known), flange->plate,
    base->nozzle and base->each sensor."""
    tfs = []
    if T_B_F is not None:
        tfs.append(transform(t, BASE, FLANGE, T_B_F))
    tfs.append(transform(t, FLANGE, PLATE, calibration.T_F_O))
    tfs.append(transform(t, BASE, NOZZLE, calibration.T_B_N))
    tfs.extend(transform(t, BASE, sid, T) for sid, T in sorted(calibration.T_B_S.items()))
    return (t, TOPIC_TF, fm.FrameTransforms(transforms=tfs))


SENSOR_RGB = {"S1": (230, 159, 0), "S2": (86, 180, 233), "S3": (0, 158, 115)}


def profile_message(t: float, sensor_id: str, points_O_mm: np.ndarray) -> tuple:
    """One raw profile registered in ``plate``, coloured by its sensor."""
    rgb = np.tile(np.array(SENSOR_RGB.get(sensor_id, (200, 200, 200)), np.uint8),
                  (len(points_O_mm), 1))
    return (t, TOPIC_PROFILES, point_cloud(t, points_O_mm, rgb))


def finding_messages(t: float, report: dict) -> list:
    """The verdict (its headline and sentences) and each process finding, as logs at ``t``."""
    from dm2.report.summary import verdict

    v = verdict(report)
    level = fm.LogLevel.Warning if v["defects"] else fm.LogLevel.Info
    out = [(t, TOPIC_FINDINGS, fm.Log(timestamp=stamp(t), level=level,
                                      message=f"verdict: {v['headline']}", name="dm2.verdict",
                                      file="", line=0))]
    for line in v["sentences"]:
        out.append((t, TOPIC_FINDINGS, fm.Log(timestamp=stamp(t), level=level,
                                              message=f"verdict: {line}", name="dm2.verdict",
                                              file="", line=0)))
    for f in (report.get("process") or {}).get("findings", []):
        out.append((t, TOPIC_FINDINGS, fm.Log(timestamp=stamp(t), level=fm.LogLevel.Info,
                                              message=f"process finding: {f}",
                                              name="dm2.process", file="", line=0)))
    return out
