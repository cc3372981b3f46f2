"""A monitoring session: the stages interleaved in stream order, messages to layer results.

The drivers build a :class:`~dm2.pipeline.pipeline.Pipeline`, which runs this object.
:class:`MonitoringSession` wires the stages of the paper's sections 5 and 6 for one build:
every message goes to the fusion :class:`~dm2.fusion.fusion.TsdfFusion`; robot states also grow
the near-net :class:`~dm2.reference.model.NearNetReference` along the executed motion; when the
fusion closes a layer, that layer's surface is compared with the reference of the same layer
(:class:`~dm2.defects.layer_analysis.LayerAnalysis`: deviation, classification, segmentation,
tracking).

The reference follows the executed path (:mod:`dm2.reference.feed`,
:mod:`dm2.reference.path_clock`): with a toolpath, each robot state advances the reference's clock
by the programmed time of the path it covered (or, with ``reference_clock = "executed"``, by the
controller's time while the spray spot progresses), so a robot that stops and keeps spraying
(a corner dwell, a reorientation stop) grows the part but not the reference. Without a toolpath
the reference integrates the controller's own clock. Where the reference grows, the fused
surface's weights are capped (:mod:`dm2.pipeline.grown_columns`).

After every fused frame set (three profiles) the active region of the measured TSDF is compared
with the reference as of the same instant (:mod:`dm2.defects.realtime`): an alarm within a second
of process time; robot states are held back until the profiles they bracket are fused.

Live streams put fusion first: ``feed(msg, defer=True)`` only fuses and notes that a comparison
is due; :meth:`MonitoringSession.catch_up` (called by the live loop whenever its inbox is empty)
integrates the held-back robot states in slices of :data:`STATE_SLICE`, runs the comparison at
the newest fused profile (frame sets that arrived meanwhile are compared once, together) and
pre-meshes the surface chunks touched so far. The reference integrates states one by one
whatever the slicing, and the surface is the same whenever chunks are meshed, so deferred and
immediate feeding give the same layer results and tracks; ``analysis_thread=True`` runs the
layer analysis on a worker thread, in layer order, off the fusion path.

The same object serves the twin, recordings and live sources: it only sees messages. The
reference of layer ``L`` is taken at the start of layer ``L + 1`` (a ``LayerMark``): exactly the
deposition of layers ``0..L``; streams without layer marks take it when the fusion closes it.
"""

from __future__ import annotations

import logging
import time
from collections import deque
from collections.abc import Callable, Iterable

import numpy as np

from dm2.core.config import MonitorConfig, ProcessConfig
from dm2.core.messages import Calibration, LayerMark, RobotState, Toolpath
from dm2.defects.footprint import PlannedOutline
from dm2.defects.layer_analysis import LayerAnalysis, LayerResult
from dm2.defects.realtime import RealtimeDeviation
from dm2.fusion.fusion import DEFAULT_MAX_DELAY_S, LayerSurface, TsdfFusion
from dm2.pipeline.events import LayerClosed, LayerStarted, Observed, SessionTiming
from dm2.pipeline.grown_columns import GrownColumns
from dm2.pipeline.layer_worker import LayerWorker
from dm2.pipeline.realtime_stage import RealtimeStage
from dm2.pipeline.seen_reference import SeenReference
from dm2.process.fit_schedule import FitSchedule
from dm2.process.process_fit import ProcessFit, process_fit_on
from dm2.reference.feed import ReferenceFeed
from dm2.reference.model import NearNetReference

log = logging.getLogger(__name__)

FRAME_SET = 3  # profiles per real-time comparison (the three cascaded profilers)
STATE_BACKLOG = 2500  # states buffered at most while no profile is fused (10 s at 250 Hz)
STATE_SLICE = 25  # robot states per reference update while catching up (0.1 s at 250 Hz)
PREMESH_EVERY_S = 0.25  # [s] wall, pre-meshing of touched surface chunks at most this often


class MonitoringSession:
    """Messages in, per-layer :class:`~dm2.defects.layer_analysis.LayerResult` out.

    Parameters
    ----------
    calibration : the calibration the pipeline trusts (``T_B_S``, ``T_F_O``, ``T_B_N``)
    monitor_cfg : fusion and deviation settings
    process : nominal process parameters (for the near-net reference and the active region)
    plate_size_mm : (Lx, Ly[, thickness]) [mm], extent of the reference height map
    toolpath : optional; splits layers when the stream carries no layer marks
    on_layer : optional callback ``f(LayerResult)`` when a layer has been analysed (from the
        worker thread with ``analysis_thread``)
    analysis_thread : analyse finished layers on a worker thread (live runs; :meth:`finish`
        waits for it: same results); without it (replays) the fusion fuses full batches only
    gates : optional :class:`~dm2.fusion.gates.InputGates` every message passes first
        (replays; a live run gates before its clock aligner); its drops join :attr:`dropped`
    """

    def __init__(self, calibration: Calibration, monitor_cfg: MonitorConfig,
                 process: ProcessConfig, plate_size_mm=(120.0, 120.0),
                 toolpath: Toolpath | None = None,
                 on_layer: Callable[[LayerResult], None] | None = None,
                 analysis_thread: bool = False, gates=None):
        self.cfg = monitor_cfg
        self.gates = gates
        self.on_layer = on_layer
        self.reference = NearNetReference(process, monitor_cfg, calibration,
                                          size_mm=tuple(plate_size_mm[:2]))
        outline = (PlannedOutline.from_toolpath(toolpath, tuple(plate_size_mm[:2]),
                                                monitor_cfg.voxel_mm)
                   if toolpath is not None else None)
        self.defects = LayerAnalysis(monitor_cfg, outline=outline)
        planned = (float(np.max(toolpath.position_O[:, 2])) if toolpath is not None
                   and len(toolpath.position_O) else None)
        self.process_fit = (ProcessFit(monitor_cfg.process_fit_rate_per_layer,
                                       monitor_cfg.process_fit_bound,
                                       monitor_cfg.process_finding_threshold, planned)
                            if process_fit_on(monitor_cfg) else None)
        self.fusion = TsdfFusion(calibration, monitor_cfg, process, toolpath=toolpath,
                                 on_layer_done=self._layer_done, defer_meshing=analysis_thread,
                                 max_delay_s=DEFAULT_MAX_DELAY_S if analysis_thread else np.inf)
        self.timing = SessionTiming()
        self.states = ReferenceFeed(self.reference, toolpath, monitor_cfg.reference_clock,
                                    monitor_cfg.dwell_speed_mm_s)
        self.realtime = RealtimeDeviation(monitor_cfg, size_mm=tuple(plate_size_mm[:2]),
                                          outline=outline)
        self._rt_profiles = 0
        self.fusion.observed_points = []
        self.seen = SeenReference(self.reference.heights_mm.shape, self.reference.cell_mm,
                                  0.5 * monitor_cfg.voxel_mm)
        self.grown = GrownColumns(self.reference.heights_mm.shape, self.reference.cell_mm,
                                  self.fusion.tsdf, monitor_cfg.deposit_weight_cap)
        self.fit = FitSchedule(self.process_fit, self.reference, self.seen, self.grown,
                               self.realtime)
        self._realtime_stage = RealtimeStage(self.realtime)
        self._no_wait = self._fit_waits = False  # catch_up: the fit waits for the worker
        self._taken_layer = -1
        self._finished = False
        self._last_premesh = 0.0
        # reference steps due at a stamp, in stream order (run when catching up if deferred)
        self._ops: deque[LayerStarted | LayerClosed] = deque()
        self._marked_layer = self.reference.layer
        self._defer_layers = bool(analysis_thread)
        self._worker = LayerWorker(self._analyse) if analysis_thread else None
        self.fit.worker = self._worker

    @property
    def results(self) -> list[LayerResult]:
        return self.defects.results

    @property
    def tracks(self):
        return self.defects.tracker.tracks

    @property
    def dropped(self) -> dict[str, int]:
        out = dict(self.fusion.dropped)
        if self.gates is not None:
            out.update({k: int(v) for k, v in self.gates.dropped.items() if v})
        if self.reference.gaps_skipped:
            out["reference_pose_gap"] = int(self.reference.gaps_skipped)
        return out

    def feed(self, msg, defer: bool = False) -> None:
        """Take one message (Profile, RobotState or LayerMark). ``defer=True`` fuses only: the
        reference update and the real-time comparison wait for :meth:`catch_up` (layer ends
        still take the reference of the finished layer at once)."""
        if self.gates is not None:
            for m, _ in self.gates.admit(msg):
                self._feed(m, defer)
            return
        self._feed(msg, defer)

    def _feed(self, msg, defer: bool) -> None:
        self.timing.messages += 1
        if isinstance(msg, RobotState):
            self.states.push(msg.stamp_s, msg.T_B_F)
        elif isinstance(msg, LayerMark) and msg.layer > self._marked_layer:
            self._marked_layer = msg.layer
            self._ops.append(LayerStarted(msg.stamp_s, msg.layer))
            self._advance(upto_s=msg.stamp_s)  # deferred too: the grown columns, before fusing on
            self.grown.update(self.reference.heights_mm)
        t0 = time.perf_counter()
        self.fusion.feed(msg)
        self._queue_observed()
        self.timing.fusion_s += time.perf_counter() - t0
        if defer:
            return
        if self.fusion.profiles_fused - self._rt_profiles >= FRAME_SET:
            self._realtime()
        elif len(self.states) >= STATE_BACKLOG:  # a stream of poses without profiles
            self._advance()

    @property
    def behind(self) -> bool:
        """True while a deferred comparison or a backlog of robot states waits."""
        return (self.fusion.profiles_fused - self._rt_profiles >= FRAME_SET
                or len(self.states) >= STATE_BACKLOG or bool(self._ops))

    def catch_up(self, should_yield: Callable[[], bool] | None = None) -> bool:
        """Run the work ``feed(..., defer=True)`` left: reference updates in slices, then one
        real-time comparison at the newest fused profile, then surface pre-meshing.

        ``should_yield()`` is asked between slices; when it returns True the method returns
        False at once (call again later). Returns True when nothing is left.
        """
        def stop() -> bool:  # a message waits, or the fit waits for the layer worker
            return self._fit_waits or (should_yield is not None and should_yield())

        self._fit_waits, self._no_wait = False, True
        try:
            if self.fusion.profiles_fused - self._rt_profiles >= FRAME_SET:
                upto = self.fusion.last_fused_stamp_s
                while not self._advance(upto_s=upto, max_states=STATE_SLICE):
                    if stop():
                        return False
                self._realtime()
            while self._ops and np.isfinite(self._ops[0].stamp_s):
                self._advance(upto_s=self._ops[0].stamp_s, max_states=STATE_SLICE)
                if stop():
                    return False
            while len(self.states) >= STATE_BACKLOG:
                self._advance(max_states=STATE_SLICE)
                if stop():
                    return False
        finally:
            self._no_wait = False
        now = time.perf_counter()
        if now - self._last_premesh >= PREMESH_EVERY_S and not stop():
            t0 = time.perf_counter()
            done = self.fusion.extractor.premesh(stop)
            self.timing.fusion_s += time.perf_counter() - t0
            if done:
                self._last_premesh = now
            return done
        return True

    def feed_all(self, messages: Iterable) -> None:
        for m in messages:
            self.feed(m)

    def finish(self) -> list[LayerResult]:
        """Flush everything, close the last layer and end the tracks."""
        if not self._finished:
            if self.gates is not None:
                for m, _ in self.gates.flush():
                    self._feed(m, False)
            self._advance()
            self.grown.update(self.reference.heights_mm, cap=False)  # as at a mark; no cap
            t0 = time.perf_counter()
            self.fusion.finish()
            self._queue_observed()
            self.timing.fusion_s += time.perf_counter() - t0
            self._advance()
            if self._worker is not None:
                self._worker.join()
            self.defects.finish()
            self._finished = True
        return self.results

    def _advance(self, upto_s: float = np.inf, max_states: int | None = None) -> bool:
        """Integrate the robot states up to ``upto_s``, running the reference steps due on the
        way in order; with ``max_states`` it returns False after that many states or after one
        step (call again). True when nothing stamped up to ``upto_s`` is left."""
        budget = max_states  # states left for this call (Observed steps are not slices)
        while self._ops and self._ops[0].stamp_s <= upto_s:
            before = len(self.states)
            if not self._flush_states(upto_s=self._ops[0].stamp_s, max_states=budget):
                return False
            if budget is not None:
                budget -= before - len(self.states)
                if budget <= 0:
                    return False
            step = self._ops.popleft()
            if isinstance(step, Observed):
                self.seen.observe(step.points_O, step.stamp_s, self.reference.heights_mm)
                self.fit.observe(step.points_O, step.stamp_s, self.reference.heights_mm)
            elif isinstance(step, LayerStarted):
                self.reference.end_layer(step.layer - 1)
                self.reference.layer = step.layer
            else:
                self._take_layer(step.layer_surface)
            if max_states is not None and not isinstance(step, Observed):
                return False
        return self._flush_states(upto_s=upto_s, max_states=budget)

    def _flush_states(self, upto_s: float = np.inf, max_states: int | None = None) -> bool:
        t0 = time.perf_counter()
        due_s = self.fit.due_s
        if due_s is not None and upto_s >= due_s:
            self._fit_waits = self._no_wait and self._worker is not None and self._worker.busy
            if self._fit_waits or not self.states.flush(due_s, max_states):
                self.timing.reference_s += time.perf_counter() - t0
                return False  # (catch_up comes back once the worker is done: no stall)
            self.fit.apply(self._taken_layer)
        done = self.states.flush(upto_s, max_states)
        self.timing.reference_s += time.perf_counter() - t0
        return done

    def _queue_observed(self) -> None:
        """Queue where the profiles fused since the last call saw the surface (in stream order
        with the layer steps, so the seen reference does not depend on the slicing)."""
        for points, stamp in self.fusion.observed_points:
            self._ops.append(Observed(float(stamp), points))
        self.fusion.observed_points.clear()

    def _realtime(self) -> None:
        """Compare the active region with the reference as of the newest fused profile."""
        self._rt_profiles = self.fusion.profiles_fused
        stamp = self.fusion.last_fused_stamp_s
        self._advance(upto_s=stamp)
        if self.states.last_T_B_F is None:
            return
        self.timing.realtime_s += self._realtime_stage.compare(
            self.fusion.tsdf, self.reference, self.states.last_T_B_F, stamp)

    def process_summary(self) -> dict:
        """The fitted process scale per layer and the process findings, for the report."""
        if self.process_fit is None:
            return {"fitted": None, "findings": []}
        return self.process_fit.summary()

    def realtime_summary(self) -> dict:
        """Real-time deviation alarms and per-frame-set latency, for the report."""
        return self._realtime_stage.summary()

    def _layer_done(self, done: LayerSurface) -> None:
        self._queue_observed()  # what the layer's own profiles saw comes first
        if self._worker is None and done.surface.vertices_O.shape[0] == 0:
            log.warning("layer %d: no surface was reconstructed; skipped", done.layer)
            return
        self._ops.append(LayerClosed(done.stamp_s if np.isfinite(done.stamp_s) else np.inf, done))
        if not self._defer_layers:
            self._advance(upto_s=self._ops[-1].stamp_s)

    def _take_layer(self, done: LayerSurface) -> None:
        """The finished layer's reference (states flushed up to its last profile), then its
        analysis (here, or queued for the worker)."""
        if self.fit.due_s is not None:  # a layer shorter than the fit's delay
            self.fit.apply(self._taken_layer)
        ref = self.reference.layers.get(done.layer)
        if ref is None:  # no layer marks in the stream: take the reference now
            ref = self.reference.end_layer(done.layer)
        stamp = None if not np.isfinite(done.stamp_s) else done.stamp_s
        since_seen = self.seen.since_seen(ref)  # (growth, where the surface is expected)
        self._taken_layer = done.layer
        self.fit.layer_taken(ref, done.stamp_s)  # its fit applies a little later (fit_schedule)
        if self._worker is None:
            self._analyse(done, ref, stamp, since_seen)
        else:  # meshed (done.surface) and analysed on the worker
            self._worker.submit(done, ref, stamp, since_seen)

    def _analyse(self, done: LayerSurface, ref, stamp, since_seen=(None, None)) -> None:
        t0 = time.perf_counter()
        surface = done.surface
        if surface.vertices_O.shape[0] == 0:
            log.warning("layer %d: no surface was reconstructed; skipped", done.layer)
            return
        result = self.defects.analyse_layer(surface, ref, done.layer, stamp, *since_seen)
        self.fit.analysed(result)  # applied when it is due (FitSchedule.apply)
        self.timing.analysis_s += time.perf_counter() - t0
        if self.on_layer is not None:
            self.on_layer(result)
