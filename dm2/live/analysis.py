"""The pipeline with what a live run adds: per-layer reports, transport drop counts,
out-of-range points and sensor dropouts.

:class:`LiveAnalysis` wraps :class:`~dm2.pipeline.pipeline.Pipeline` (the same object
``dm2 run`` drives in process, so a live run and an in-process run of the same stream give the
same layers and tracks), gives the fusion stage the plate's box so points far outside count
``out_of_range``, notes sensors silent for longer than allowed (``sensor_dropout`` events) and,
with an output folder, rewrites the report after every analysed layer. With ``live=True`` the
pipeline fuses first and catches up when asked (:meth:`LiveAnalysis.catch_up`, the live loop's
idle moments) and analyses finished layers on its worker thread. Interim reports are written
from a snapshot of the results and tracks by a child process (:mod:`dm2.live.report_process`,
fed by a background thread), so a slow report (plots) never holds up the fusion of the profiles
arriving meanwhile, not even through the interpreter lock; the final report is written in the
caller's thread after the last one finished.
"""

from __future__ import annotations

import copy
import logging
import threading
import time
from collections import Counter
from pathlib import Path

import numpy as np

from dm2.core.messages import Profile

log = logging.getLogger(__name__)

OUT_OF_RANGE_MARGIN_MM = 5.0
MAX_PART_HEIGHT_MM = 200.0
# Live runs fuse on the loop's own thread: the second core already serves the socket threads,
# the recorder, the layer analysis and the report process, and handing a batch to a fusion
# thread made the loop give up the interpreter lock and wait to get it back (the field is the
# same either way). Measured at 10x on 2 cores: p50 15 -> 5 ms, p99 51 -> 22 ms.
LIVE_TSDF_THREADS = 1


class LiveAnalysis:
    """The pipeline plus live bookkeeping for one message stream.

    Parameters
    ----------
    calibration : dm2.core.messages.Calibration
    monitor_cfg, process : dm2.core.config MonitorConfig and ProcessConfig
    plate_size_mm : (Lx, Ly, thickness) [mm]; points outside the plate's box (plus a margin,
        up to ``MAX_PART_HEIGHT_MM``) count ``out_of_range``
    toolpath : optional dm2.core.messages.Toolpath (layer changes when there are no marks)
    out_dir : folder for the report (rewritten after each layer) or None
    config_toml : resolved configuration text written beside the report
    max_sensor_gap_s : float [s], a sensor silent longer than this counts ``sensor_dropout``
    meta : extra entries for report.json's ``meta``
    live : fusion first: reference and real-time comparison wait for :meth:`catch_up`, layer
        analysis runs on a worker thread, fusion on the calling thread only
        (``LIVE_TSDF_THREADS``); same layer results and tracks
    """

    def __init__(self, calibration, monitor_cfg, process, plate_size_mm, toolpath=None,
                 out_dir: str | Path | None = None, config_toml: str | None = None,
                 max_sensor_gap_s: float = 1.0, meta: dict | None = None, live: bool = False):
        from dm2.pipeline.pipeline import Pipeline

        Lx, Ly, th = (float(v) for v in plate_size_mm)
        m = OUT_OF_RANGE_MARGIN_MM
        self.pipeline = Pipeline(calibration, monitor_cfg, process, plate_size_mm=(Lx, Ly),
                                 toolpath=toolpath, on_layer=self._on_layer, live=live)
        self.live = bool(live)
        if self.live:
            self.pipeline.fusion.tsdf.threads = LIVE_TSDF_THREADS
        self.pipeline.fusion.bounds_O = (np.array([-m, -m, -th - m]),
                                         np.array([Lx + m, Ly + m, MAX_PART_HEIGHT_MM]))
        self.out_dir = None if out_dir is None else Path(out_dir)
        self.config_toml = config_toml
        self.meta = dict(meta or {})
        self.max_sensor_gap_s = float(max_sensor_gap_s)
        self.extra_dropped: Counter = Counter()
        self.drop_sources: list = []  # callables returning dicts of transport drops
        self.layer_listeners: list = []  # callables f(LayerResult), e.g. a live 3D view
        self.events: Counter = Counter()
        self.meta_sources: dict = {}  # report.json meta key -> callable giving its value
        self.report_s = 0.0
        self._last_profile_s: dict[str, float] = {}
        self._finished = False
        self._snapshot = None
        self._wake = threading.Condition()
        self._writer: threading.Thread | None = None
        self._child = None  # ReportProcess writing the interim reports
        if self.live and self.out_dir is not None:
            self._start_report_process()

    @property
    def fusion(self):
        return self.pipeline.fusion

    @property
    def results(self):
        return self.pipeline.results

    @property
    def tracks(self):
        return self.pipeline.tracks

    def feed(self, msg) -> None:
        """One message of any kind (bad ones are counted, never raised)."""
        if isinstance(msg, Profile):
            self._watch_dropout(msg)
        self.pipeline.feed(msg)

    def catch_up(self, should_yield=None) -> bool:
        """Deferred pipeline work (see Pipeline.catch_up); True when none is left."""
        return self.pipeline.catch_up(should_yield)

    def _watch_dropout(self, p: Profile) -> None:
        last = self._last_profile_s.get(p.sensor_id)
        if last is not None and p.stamp_s - last > self.max_sensor_gap_s:
            self.events["sensor_dropout"] += 1
            log.warning("sensor %s was silent for %.2f s (allowed %.2f s)", p.sensor_id,
                        p.stamp_s - last, self.max_sensor_gap_s)
        if last is None or p.stamp_s > last:
            self._last_profile_s[p.sensor_id] = p.stamp_s

    def _on_layer(self, result) -> None:
        for listener in self.layer_listeners:
            listener(result)
        if self.out_dir is None:
            return
        snap = self._take_snapshot()
        with self._wake:
            self._snapshot = snap  # a newer snapshot replaces one not yet written
            self._wake.notify()
        if self._writer is None:
            self._writer = threading.Thread(target=self._write_loop, name="report-writer",
                                            daemon=True)
            self._writer.start()

    def _write_loop(self) -> None:
        while True:
            with self._wake:
                while self._snapshot is None:
                    self._wake.wait()
                snap, self._snapshot = self._snapshot, None
            if snap == "stop":
                return
            try:
                self._write_interim(*snap)
            except Exception:  # noqa: BLE001 - a failed interim report must not end the run
                log.exception("writing the interim report failed")

    def _start_report_process(self) -> None:
        """Start the report child (before the stream: its imports take about a second)."""
        from dm2.live.report_process import ReportProcess, ReportProcessError

        self._child = ReportProcess()
        try:
            self._child.start()
        except (OSError, ReportProcessError) as exc:  # retried at the first interim report
            log.warning("report process could not be started now: %s", exc)

    def _write_interim(self, results, tracks, dropped, timing, meta, maps) -> None:
        """An interim report, written by the report child process (falls back to this
        thread when the child cannot run)."""
        from dm2.report.report_content import ReportContent

        if self._child is None:
            from dm2.live.report_process import ReportProcess

            self._child = ReportProcess()
        try:
            self.report_s += self._child.write(
                self.out_dir, results, tracks,
                ReportContent(config_toml=self.config_toml, dropped=dropped, timing=timing,
                              map_layers=maps, meta=meta))
        except OSError as exc:  # the child could not be started
            log.warning("report process unavailable (%s): writing in this process", exc)
            self._write(results, tracks, dropped, timing, meta, maps)

    def _take_snapshot(self):
        results = list(self.results)
        mon = self.fusion
        meta = {**self.meta, "events": dict(self.events), "profiles_fused": mon.profiles_fused,
                "points_fused": mon.points_fused, "complete": self._finished,
                **{k: f() for k, f in self.meta_sources.items()}}
        timing = self.pipeline.timing(report_s=self.report_s)
        maps = None if self._finished else ([results[-1].layer] if results else [])
        return results, copy.deepcopy(self.tracks), self._dropped_now(), timing, meta, maps

    def _dropped_now(self) -> dict[str, int]:
        """:attr:`dropped` read from any thread (the counters may grow meanwhile)."""
        for _ in range(10):
            try:
                return self.dropped
            except RuntimeError:  # a counter gained a key while it was read
                continue
        return self.dropped

    @property
    def dropped(self) -> dict[str, int]:
        """Drops by reason: the pipeline's (sync stage) plus the transport's."""
        out = Counter(self.pipeline.dropped)
        out.update(self.extra_dropped)
        for source in self.drop_sources:
            out.update(source())
        return {k: int(v) for k, v in sorted(out.items()) if v}

    def write_report(self) -> dict:
        """Rewrite the report folder with every layer analysed so far (in this thread)."""
        return self._write(*self._take_snapshot())

    def _write(self, results, tracks, dropped, timing, meta, maps) -> dict:
        t0 = time.perf_counter()  # the live report holds no realtime/process sections
        report = self.pipeline.write_outputs(self.out_dir, results=results, tracks=tracks,
                                             config_toml=self.config_toml, dropped=dropped,
                                             sections={}, timing=timing, map_layers=maps,
                                             meta=meta, toolpath=None)
        self.report_s += time.perf_counter() - t0
        return report

    def _stop_writer(self) -> None:
        if self._writer is not None:
            with self._wake:
                self._snapshot = "stop" if self._snapshot is None else self._snapshot
                self._wake.notify()
            while self._writer.is_alive():
                with self._wake:
                    if self._snapshot is None:
                        self._snapshot = "stop"
                        self._wake.notify()
                self._writer.join(timeout=0.1)
            self._writer = None
        if self._child is not None:
            self._child.close()
            self._child = None

    def close(self) -> None:
        """Stop the interim report writer and its child process without a final report."""
        self._stop_writer()

    def finish(self) -> dict | None:
        """End of stream: analyse the last layer, end the tracks, write the final report."""
        if self._finished:
            return None
        self.pipeline.finish()
        self._finished = True
        self._stop_writer()
        if self.out_dir is not None:
            return self.write_report()
        return None

    def summary(self) -> list[tuple[int, str]]:
        """``(track id, kind)`` of every track, in id order."""
        return [(t.id, t.kind) for t in self.tracks]
