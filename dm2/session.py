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
from dm2.reference import NearNetReference

log = logging.getLogger(__name__)

STATE_BATCH = 250  # robot states integrated into the reference per call (1 s at 250 Hz)


@dataclass
class SessionTiming:
    """Wall seconds spent per stage, summed over the run."""

    fusion_s: float = 0.0
    reference_s: float = 0.0
    analysis_s: float = 0.0
    messages: int = 0
    extra: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return {"fusion_s": self.fusion_s, "reference_s": self.reference_s,
                "analysis_s": self.analysis_s, "messages": self.messages, **self.extra}


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
            if len(self._states_t) >= STATE_BATCH:
                self._flush_states()
        elif isinstance(msg, LayerMark):
            self._flush_states()
            if msg.layer > self.reference.layer:
                self.reference.end_layer(msg.layer - 1)
                self.reference.layer = msg.layer
        t0 = time.perf_counter()
        self.monitor.feed(msg)
        self.timing.fusion_s += time.perf_counter() - t0

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

    def _flush_states(self) -> None:
        if not self._states_t:
            return
        t0 = time.perf_counter()
        stamps = np.asarray(self._states_t)
        poses = np.stack(self._states_T)
        self._states_t.clear()
        self._states_T.clear()
        order = np.argsort(stamps, kind="stable")
        stamps, poses = stamps[order], poses[order]
        # late or duplicated states cannot rewind the reference
        keep = np.concatenate([[True], np.diff(stamps) > 0]) & (stamps > self._last_state_s)
        if np.any(keep):
            stamps, poses = stamps[keep], poses[keep]
            self._last_state_s = float(stamps[-1])
            if self.progress is not None:  # programmed timing along the executed path
                spots, _ = self.reference.spot_O(poses)
                stamps = self._nominal_s + np.cumsum(self.progress.advance(spots))
                self._nominal_s = float(stamps[-1])
            self.reference.add_states(stamps, poses)
        self.timing.reference_s += time.perf_counter() - t0

    def _layer_done(self, done: LayerSurface) -> None:
        if done.surface.vertices_O.shape[0] == 0:
            log.warning("layer %d: no surface was reconstructed; skipped", done.layer)
            return
        self._flush_states()
        ref = self.reference.layers.get(done.layer)
        if ref is None:  # no layer marks in the stream: take the reference now
            ref = self.reference.end_layer(done.layer)
        t0 = time.perf_counter()
        stamp = None if not np.isfinite(done.stamp_s) else done.stamp_s
        result = self.defects.analyse_layer(done.surface, ref, done.layer, stamp)
        self.timing.analysis_s += time.perf_counter() - t0
        if self.on_layer is not None:
            self.on_layer(result)
