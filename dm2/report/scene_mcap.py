"""``scene.mcap``: a run's scene in Foxglove's schemas, on the run's own clock.

The scene holds, each on its topic (:mod:`dm2.report.scene_messages`): the fused surface of
each layer as a point cloud coloured by signed deviation (``/dm2/surface``), the reference
beneath it (``/dm2/reference``), the tracks as labelled boxes (``/dm2/tracks``) with one plot
row per track and layer (``/dm2/track_stats``), the real-time alarms as logs
(``/dm2/alarms``) and markers (``/dm2/alarm_markers``), the frames (``/tf``: base, flange,
plate, nozzle, S1..S3), the raw profiles registered in the plate frame (``/dm2/profiles``,
decimated by :mod:`dm2.report.scene_inputs`) and the verdict with the process findings
(``/dm2/findings``). Every message's log time is its stamp on the run's clock (the clock of
the run's input recording), so the file plays back in step with it; each topic's messages are
written in stamp order.

:class:`SceneChannels` is one foxglove-sdk context with these channels: the same object
feeds an MCAP file (:func:`write_scene_mcap`) or a live WebSocket server
(:mod:`dm2.view.foxglove_live`).
"""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path

import foxglove
import numpy as np
from foxglove import channels as fc

from dm2.report import scene_messages as sm
from dm2.report.outdir import add_to_manifest, owned_files

log = logging.getLogger(__name__)

SCENE_NAME = "scene.mcap"
LAYOUT_FILE = Path(__file__).with_name("foxglove-layout.json")


class SceneChannels:
    """The scene's channels in a context of their own (see the module docstring)."""

    def __init__(self):
        self.context = foxglove.Context()
        ctx = self.context
        self.channels = {
            sm.TOPIC_SURFACE: fc.PointCloudChannel(sm.TOPIC_SURFACE, context=ctx),
            sm.TOPIC_REFERENCE: fc.PointCloudChannel(sm.TOPIC_REFERENCE, context=ctx),
            sm.TOPIC_PROFILES: fc.PointCloudChannel(sm.TOPIC_PROFILES, context=ctx),
            sm.TOPIC_TRACKS: fc.SceneUpdateChannel(sm.TOPIC_TRACKS, context=ctx),
            sm.TOPIC_ALARM_MARKERS: fc.SceneUpdateChannel(sm.TOPIC_ALARM_MARKERS, context=ctx),
            sm.TOPIC_ALARMS: fc.LogChannel(sm.TOPIC_ALARMS, context=ctx),
            sm.TOPIC_FINDINGS: fc.LogChannel(sm.TOPIC_FINDINGS, context=ctx),
            sm.TOPIC_TF: fc.FrameTransformsChannel(sm.TOPIC_TF, context=ctx),
            sm.TOPIC_TRACK_STATS: foxglove.Channel(
                sm.TOPIC_TRACK_STATS, context=ctx, message_encoding="json",
                schema=foxglove.Schema(name=sm.TRACK_STATS_SCHEMA_NAME, encoding="jsonschema",
                                       data=json.dumps(sm.TRACK_STATS_SCHEMA).encode())),
        }

    def log(self, items, log_time: bool = True) -> None:
        """Log ``(stamp_s, topic, message)`` items; ``log_time``: stamped with the run's clock
        (a recording), else with the host's clock (a live server)."""
        for t, topic, msg in items:
            ch = self.channels[topic]
            if log_time:
                ch.log(msg, log_time=max(int(round(t * 1e9)), 0))
            else:
                ch.log(msg)


def scene_items(results, report: dict | None, calibration, tap=None,
                limit_mm: float = 1.0, alarms: list | None = None) -> list:
    """Every message of a finished run's scene, sorted by stamp (stable: a topic's messages
    keep their order). ``report``: the run's report.json content (its alarms, verdict and
    findings; None where the run was not analysed). ``tap``: the run's
    :class:`~dm2.report.scene_inputs.StreamTap`, for the robot poses and raw profiles
    (without it the frames are written once, without the flange's motion). ``alarms``: the
    real-time alarms (report.json ``realtime.alarms`` entries) where the report holds none
    (a live report)."""
    items = []
    tops = []  # (stamp, top of the part) per finished layer, for the alarm markers' height
    for r in results:
        items.extend(sm.layer_messages(r, limit_mm))
        v = r.deviation.vertices_O
        tops.append((float(r.deviation.stamp_s), float(v[:, 2].max()) if len(v) else 0.0))
    tops.sort()
    if alarms is None:
        alarms = ((report or {}).get("realtime") or {}).get("alarms", [])
    for k, alarm in enumerate(alarms):
        z = max([0.0] + [z for t, z in tops if t <= alarm["stamp_s"]])
        items.extend(sm.alarm_messages(k, alarm, z))
    stamps = [t for t, _, _ in items]
    if tap is not None and tap.pose_stamps_s:
        for t, T_B_F in zip(tap.pose_stamps_s, tap.poses_T_B_F, strict=True):
            items.append(sm.frame_messages(t, calibration, T_B_F))
        items.extend(sm.profile_message(t, sid, pts)
                     for t, sid, pts in tap.registered(calibration))
        stamps += tap.pose_stamps_s
    else:
        items.append(sm.frame_messages(min(stamps, default=0.0), calibration, None))
    if report is not None:
        items.extend(sm.finding_messages(max(stamps, default=0.0), report))
    order = np.argsort([t for t, _, _ in items], kind="stable")
    return [items[i] for i in order]


def write_scene_mcap(path: str | Path, items) -> Path:
    """Write ``items`` (:func:`scene_items`) to the MCAP file ``path`` (replaced)."""
    path = Path(path)
    channels = SceneChannels()
    with foxglove.open_mcap(path, allow_overwrite=True, context=channels.context) as writer:
        writer.write_metadata("dm2", {"layout": LAYOUT_FILE.name,
                                      "units": "m in the scene, mm in named fields"})
        channels.log(items)
    return path


def add_scene_to_run(run_dir: str | Path, items, command: str | None = None) -> Path | None:
    """Write ``scene.mcap`` into the run folder and list it in its manifest; a
    ``scene.mcap`` there that dm2 did not write is left as it is (a warning, no scene)."""
    run_dir = Path(run_dir)
    dest = run_dir / SCENE_NAME
    owned = owned_files(run_dir) or set()
    if (dest.exists() or dest.is_symlink()) and SCENE_NAME not in owned:
        log.warning("%s was not written by dm2 and is left as it is; no scene recording "
                    "written", dest)
        return None
    tmp = run_dir / f".{SCENE_NAME}.{os.getpid()}.tmp"
    try:
        write_scene_mcap(tmp, items)
        os.replace(tmp, dest)
    finally:
        tmp.unlink(missing_ok=True)
    add_to_manifest(run_dir, [SCENE_NAME], command=command)
    return dest
