"""A monitoring session: the whole pipeline from messages to per-layer defect results.

:class:`MonitoringSession` wires the stages of the paper's sections 5 and 6 for one build:
every message goes to the fusion :class:`~dm2.pipeline.Monitor`; robot states also grow the
near-net :class:`~dm2.reference.NearNetReference` along the executed motion; when the monitor
closes a layer, that layer's surface is compared with the reference of the same layer
(:class:`~dm2.defects.DefectMonitor`: deviation, classification, segmentation, tracking).

The reference follows the executed path at the programmed process (:mod:`dm2.progress`): with
a toolpath, each robot state advances the nominal clock by the programmed time of the path it
covered, so a robot that stops and keeps spraying (a corner dwell) grows the part but not the
reference. Without a toolpath the reference integrates the controller's own clock.

After every fused frame set (three profiles) the active region of the measured TSDF is compared
with the reference as of the same instant (:mod:`dm2.realtime`), so a defect raises an alarm
within a second of process time, before its layer ends; robot states are held back until the
profiles they bracket are fused, so the reference never runs ahead of the measurement.

The same object serves the twin in process, recordings and live sources: it only sees
messages. The reference of layer ``L`` is taken when the stream reports the start of layer
``L + 1`` (a ``LayerMark``), so it holds exactly the deposition of layers ``0..L``; streams
without layer marks take it when the monitor closes the layer.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

import numpy as np

from dm2.config import MonitorConfig, ProcessConfig
from dm2.defects import DefectMonitor, LayerResult
from dm2.messages import Calibration, LayerMark, RobotState, Toolpath
from dm2.pipeline import LayerSurface, Monitor
from dm2.progress import ToolpathProgress
from dm2.realtime import RealtimeDeviation
from dm2.reference import NearNetReference

log = logging.getLogger(__name__)

FRAME_SET = 3  # profiles per real-time comparison (the three cascaded profilers)
STATE_BACKLOG = 2500  # states buffered at most while no profile is fused (10 s at 250 Hz)


@dataclass
class SessionTiming:
    """Wall seconds spent per stage, summed over the run."""

    fusion_s: float = 0.0
    reference_s: float = 0.0
    analysis_s: float = 0.0
    realtime_s: float = 0.0
    messages: int = 0
    extra: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return {"fusion_s": self.fusion_s, "reference_s": self.reference_s,
                "analysis_s": self.analysis_s, "realtime_s": self.realtime_s,
                "messages": self.messages, **self.extra}


class MonitoringSession:
    """Messages in, per-layer :class:`~dm2.defects.LayerResult` out.

    Parameters
    ----------
    calibration : the calibration the pipeline trusts (``T_B_S``, ``T_F_O``, ``T_B_N``)
    monitor_cfg : fusion and deviation settings
    process : nominal process parameters (for the near-net reference and the active region)
    plate_size_mm : (Lx, Ly[, thickness]) [mm], extent of the reference height map
    toolpath : optional; splits layers when the stream carries no layer marks
    on_layer : optional callback ``f(LayerResult)`` when a layer has been analysed
    """

    def __init__(self, calibration: Calibration, monitor_cfg: MonitorConfig,
                 process: ProcessConfig, plate_size_mm=(120.0, 120.0),
                 toolpath: Toolpath | None = None,
                 on_layer: Callable[[LayerResult], None] | None = None):
        self.cfg = monitor_cfg
        self.on_layer = on_layer
        self.reference = NearNetReference(process, monitor_cfg, calibration,
                                          size_mm=tuple(plate_size_mm[:2]))
        self.defects = DefectMonitor(monitor_cfg)
        self.monitor = Monitor(calibration, monitor_cfg, process, toolpath=toolpath,
                               on_layer_done=self._layer_done)
        self.timing = SessionTiming()
        self._states_t: list[float] = []
        self._states_T: list[np.ndarray] = []
        self._last_state_s = -np.inf
        self._last_T_B_F: np.ndarray | None = None
        self.realtime = RealtimeDeviation(monitor_cfg, size_mm=tuple(plate_size_mm[:2]))
        self._rt_profiles = 0
        self._rt_latency_s: list[float] = []
        self.progress = ToolpathProgress(toolpath) if toolpath is not None else None
        self._nominal_s = 0.0
        self._finished = False

    @property
    def results(self) -> list[LayerResult]:
        return self.defects.results

    @property
    def tracks(self):
        return self.defects.tracker.tracks

    @property
    def dropped(self) -> dict[str, int]:
        out = dict(self.monitor.dropped)
        if self.reference.gaps_skipped:
            out["reference_pose_gap"] = int(self.reference.gaps_skipped)
        return out

    def feed(self, msg) -> None:
        """Take one message (Profile, RobotState or LayerMark)."""
        self.timing.messages += 1
        if isinstance(msg, RobotState):
            self._states_t.append(msg.stamp_s)
            self._states_T.append(msg.T_B_F)
        elif isinstance(msg, LayerMark) and msg.layer > self.reference.layer:
            self._flush_states(upto_s=msg.stamp_s)
            self.reference.end_layer(msg.layer - 1)
            self.reference.layer = msg.layer
        t0 = time.perf_counter()
        self.monitor.feed(msg)
        self.timing.fusion_s += time.perf_counter() - t0
        if self.monitor.profiles_fused - self._rt_profiles >= FRAME_SET:
            self._realtime()
        elif len(self._states_t) >= STATE_BACKLOG:  # a stream of poses without profiles
            self._flush_states()

    def feed_all(self, messages: Iterable) -> None:
        for m in messages:
            self.feed(m)

    def finish(self) -> list[LayerResult]:
        """Flush everything, close the last layer and end the tracks."""
        if not self._finished:
            self._flush_states()
            t0 = time.perf_counter()
            self.monitor.finish()
            self.timing.fusion_s += time.perf_counter() - t0
            self.defects.finish()
            self._finished = True
        return self.results

    def _flush_states(self, upto_s: float = np.inf) -> None:
        """Integrate the buffered robot states stamped up to ``upto_s`` into the reference."""
        if not self._states_t:
            return
        t0 = time.perf_counter()
        stamps = np.asarray(self._states_t)
        order = np.argsort(stamps, kind="stable")
        stamps = stamps[order]
        n = int(np.searchsorted(stamps, upto_s, side="right"))
        if n == 0:
            return
        poses = np.stack([self._states_T[i] for i in order[:n]])
        rest = order[n:]
        self._states_t = [self._states_t[i] for i in rest]
        self._states_T = [self._states_T[i] for i in rest]
        stamps = stamps[:n]
        # late or duplicated states cannot rewind the reference
        keep = np.concatenate([[True], np.diff(stamps) > 0]) & (stamps > self._last_state_s)
        if np.any(keep):
            stamps, poses = stamps[keep], poses[keep]
            self._last_state_s = float(stamps[-1])
            self._last_T_B_F = poses[-1]
            if self.progress is not None:  # programmed timing along the executed path
                spots, _ = self.reference.spot_O(poses)
                stamps = self._nominal_s + np.cumsum(self.progress.advance(spots))
                self._nominal_s = float(stamps[-1])
            self.reference.add_states(stamps, poses)
        self.timing.reference_s += time.perf_counter() - t0

    def _realtime(self) -> None:
        """Compare the active region with the reference as of the newest fused profile."""
        self._rt_profiles = self.monitor.profiles_fused
        stamp = self.monitor.last_fused_stamp_s
        self._flush_states(upto_s=stamp)
        if self._last_T_B_F is None:
            return
        t0 = time.perf_counter()
        spot_O, _ = self.reference.spot_O(self._last_T_B_F)
        frame = self.realtime.update_from_tsdf(self.monitor.tsdf, spot_O, stamp,
                                               self.reference)
        for alarm in frame.alarms:
            log.warning("real-time: %s of %.1f mm2 at (%.1f, %.1f) mm, %.2f s after its first "
                        "flag", alarm.kind, alarm.area_mm2, *alarm.centroid_xy_O,
                        alarm.stamp_s - alarm.first_flag_s)
        dt = time.perf_counter() - t0
        self.timing.realtime_s += dt
        self._rt_latency_s.append(dt)

    def realtime_summary(self) -> dict:
        """Real-time deviation alarms and per-frame-set latency, for the report."""
        lat = np.asarray(self._rt_latency_s)
        return {
            "frame_sets": int(lat.size),
            "latency_ms_p50": float(np.percentile(lat, 50) * 1e3) if lat.size else None,
            "latency_ms_p99": float(np.percentile(lat, 99) * 1e3) if lat.size else None,
            "alarms": [{"stamp_s": a.stamp_s, "kind": a.kind, "area_mm2": a.area_mm2,
                        "centroid_xy_O_mm": [float(c) for c in a.centroid_xy_O],
                        "first_flag_s": a.first_flag_s,
                        "delay_s": a.stamp_s - a.first_flag_s} for a in self.realtime.alarms],
        }

    def _layer_done(self, done: LayerSurface) -> None:
        if done.surface.vertices_O.shape[0] == 0:
            log.warning("layer %d: no surface was reconstructed; skipped", done.layer)
            return
        self._flush_states(upto_s=done.stamp_s if np.isfinite(done.stamp_s) else np.inf)
        ref = self.reference.layers.get(done.layer)
        if ref is None:  # no layer marks in the stream: take the reference now
            ref = self.reference.end_layer(done.layer)
        t0 = time.perf_counter()
        stamp = None if not np.isfinite(done.stamp_s) else done.stamp_s
        result = self.defects.analyse_layer(done.surface, ref, done.layer, stamp)
        self.timing.analysis_s += time.perf_counter() - t0
        if self.on_layer is not None:
            self.on_layer(result)
