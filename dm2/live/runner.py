"""The live run: sources -> inbox -> clock alignment -> recording + analysis -> reports.

:class:`LiveRunner` owns the sockets (EGM over UDP, profile bridges over TCP, optional
scanCONTROL sensors), one bounded :class:`~dm2.live.inbox.Inbox` they all feed, the
:class:`~dm2.live.clock.ClockAligner`, the crash-safe :class:`~dm2.live.recorder.LiveRecorder`
(``<out>/live.mcap``, the stream as the pipeline receives it, after the plausibility gates of
:mod:`dm2.fusion.gates`, stamps on the robot's clock,
written by a :class:`~dm2.live.recorder.RecorderThread` off the hot path) and
a :class:`~dm2.live.analysis.LiveAnalysis` that rewrites ``<out>/report`` (report.json and the
rest, replaced atomically) after every layer. ``report.json``'s ``dropped`` merges the
transport's drop counts with the pipeline's. Nothing here imports the twin: the same code
runs against a real cell.

Latency policy: fusion comes first. The session only fuses as messages arrive; the near-net
reference, the real-time comparison (at the newest fused profile: frame sets that arrived
while the loop was busy are compared once, together) and surface pre-meshing run when the
inbox is empty, in slices that give way as soon as a message arrives; layer analysis runs on
the session's worker thread. While the loop is caught up, a profile is fused as soon as the
robot state after its stamp has arrived (batches of one, so it never waits for its frame set
while the loop catches up); while it is behind, full batches and the monitor's batch delay let
fusion run in larger, cheaper batches until it has caught up. For the run, the objects that
exist when the sources open are frozen out of the cyclic garbage collector (``gc.freeze``,
thawed when the run finishes or closes): a full collection over them took 130-180 ms, a stall no
profile should wait behind.
:attr:`LiveRunner.latencies_s` holds socket-arrival to fused for every profile fused while the
stream runs (matched by sensor and stamp, so dropped profiles never count), and
:attr:`LiveRunner.inbox_waits_s` the part of it spent in the inbox (the loop busy with other
messages or deferred work; the rest is waiting for a robot state after the profile's stamp or
for its batch, and fusion);
:attr:`LiveRunner.held_by_gates` flags, for each of them, a profile the plausibility gates held
before releasing it (a source's first ``stamp_seed`` messages wait for the clock seed; messages
of a clock step wait for its confirmation), so its latency includes that deliberate hold;
:attr:`LiveRunner.fused_at_end` counts those fused only when the run ended (the last profiles
of a stream wait for a robot state after their stamp, which never comes),
:attr:`LiveRunner.busy_s` the time spent handling messages and catching up.
"""

from __future__ import annotations

import gc
import logging
import threading
import time
from collections import Counter, OrderedDict, deque
from pathlib import Path

from dm2.core.messages import LayerMark, MessageError, Profile, RobotState
from dm2.fusion.gates import InputGates
from dm2.live.analysis import LiveAnalysis
from dm2.live.clock import ClockAligner
from dm2.live.config import CellFile, parse_host_port
from dm2.live.inbox import Inbox
from dm2.live.streams import StreamGuard

log = logging.getLogger(__name__)

RECORDING_NAME = "live.mcap"
REPORT_DIR = "report"
MAX_UNFUSED = 4096  # arrival times kept for profiles not fused yet (latency accounting)


class LiveRunner:
    """A continuous monitoring run on live sources.

    Parameters
    ----------
    cell : the cell file (calibration and toolpath paths already resolved)
    out_dir : run folder (report, recording)
    cell_toml : the cell file's text, stored beside the report and in the recording
    record : write ``<out_dir>/live.mcap``
    """

    def __init__(self, cell: CellFile, out_dir: str | Path, *, cell_toml: str | None = None,
                 record: bool = True):
        from dm2.core.calibration_io import calibration_to_toml, read_calibration_toml

        self.cell = cell
        self.out_dir = Path(out_dir)
        self.calibration = read_calibration_toml(cell.calibration)
        self.toolpath = None
        attachments = {"calibration.toml": calibration_to_toml(self.calibration).encode()}
        if cell.toolpath is not None:
            from dm2.toolpath.formats import format_csv, read_csv

            self.toolpath = read_csv(cell.toolpath)
            attachments["toolpath.csv"] = format_csv(self.toolpath).encode()
        if cell_toml is not None:
            attachments["cell.toml"] = cell_toml.encode()
        live = cell.live
        self.inbox = Inbox(live.queue_size)
        self.gates = InputGates(cell.monitor.gates)
        self.aligner = ClockAligner(live.clock_tolerance_s)
        self.analysis = LiveAnalysis(self.calibration, cell.monitor, cell.process,
                                      cell.plate_size_mm, toolpath=self.toolpath,
                                      out_dir=self.report_dir, config_toml=cell_toml,
                                      max_sensor_gap_s=live.max_sensor_gap_s,
                                      meta={"mode": "live", "cell": cell.name}, live=True)
        self.streams = StreamGuard(live.max_sensor_gap_s)
        self.kept: Counter = Counter()  # per stream: robot states past the gates, profiles fused
        self.analysis.drop_sources += [lambda: self.inbox.dropped, lambda: self.gates.dropped,
                                       lambda: self.aligner.dropped, lambda: self.streams.dropped]
        self.analysis.meta_sources["streams"] = self.stream_report
        self.recorder = None
        if record:
            from dm2.live.recorder import LiveRecorder, RecorderThread

            self.out_dir.mkdir(parents=True, exist_ok=True)
            recorder = LiveRecorder(self.recording_path, attachments=attachments,
                                    chunk_s=live.chunk_s)
            recorder.write_static_tf(self.calibration)
            self.recorder = RecorderThread(recorder, maxsize=live.queue_size)
            self.analysis.drop_sources.append(lambda: self.recorder.dropped)
        self.sources: list = []
        self.latencies_s: list[float] = []  # socket arrival -> fused, per fused profile
        # of which socket arrival -> taken from the inbox and released by the clock aligner
        self.inbox_waits_s: list[float] = []
        self.held_by_gates: list[bool] = []  # per latency: held by the gates before release
        self.fused_at_end = 0  # profiles fused only by finish()
        # (sensor_id, stamp_s) -> (arrival_s, released by the gates [s, monotonic], held by them)
        self._arrivals: OrderedDict = OrderedDict()
        self.analysis.fusion.fused_log = deque()
        self.messages_in = 0
        self.busy_s = 0.0  # [s] the loop spent handling messages (vs waiting for them)
        self.max_step_s = 0.0  # [s] longest single message (a layer end, typically)
        self._last_data = None
        self._finished = False
        self._frozen = False  # objects frozen out of the cyclic collector for the run

    @property
    def report_dir(self) -> Path:
        return self.out_dir / REPORT_DIR

    @property
    def recording_path(self) -> Path:
        return self.out_dir / RECORDING_NAME

    # --------------------------------------------------------------------------- sources
    def open_sources(self) -> dict[str, tuple]:
        """Bind the configured sources and start their threads; returns their addresses.

        OSError (``ScanControlError`` included) when a socket or sensor cannot be opened; the
        sources opened so far are closed again."""
        from dm2.live.egm_source import EgmSource
        from dm2.live.tcp_profiles import ProfileServer

        self._freeze_heap()  # before the first message can arrive: a collection stalls it
        live = self.cell.live
        try:
            host, port = parse_host_port(live.egm, "live.egm")
            egm = EgmSource(self.inbox, host, port, controllers=live.controllers,
                            max_datagram_bytes=live.max_datagram_bytes,
                            schema=live.egm_schema, layer_dnum=live.egm_layer_dnum).start()
            self.sources.append(egm)
            host, port = parse_host_port(live.profiles, "live.profiles")
            prof = ProfileServer(self.inbox, host, port, bridges=live.bridges,
                                 max_frame_bytes=live.max_frame_bytes,
                                 idle_timeout_s=live.bridge_idle_s)
            prof.on_close.append(self.streams.source_closed)
            prof.start()
            self.sources.append(prof)
            addresses = {"egm": egm.address, "profiles": prof.address}
            if live.scancontrol:
                from dm2.live.scancontrol import ScanControlSource, load_wrapper

                llt = load_wrapper()
                for sensor in live.scancontrol:
                    src = ScanControlSource(self.inbox, sensor.sensor_id, sensor.serial,
                                            sensor.resolution, llt=llt, stamp=sensor.stamp,
                                            exposure_us=sensor.exposure_us,
                                            idle_us=sensor.idle_us)
                    self.sources.append(src.start())
                    addresses[f"scancontrol {sensor.sensor_id}"] = src.address
        except BaseException:
            for src in self.sources:
                src.close()
            self.sources.clear()
            raise
        return addresses

    # --------------------------------------------------------------------------- the loop
    def process(self, msg, source: str, arrival_s: float) -> None:
        """Handle one inbox item: plausibility gates, align clocks, record, analyse."""
        self.messages_in += 1
        if not self.streams.admit(msg, source, arrival_s):
            return  # duplicate_source
        for m, arrival in self.gates.admit(msg, arrival_s):
            self._aligned(m, arrival, held=m is not msg)  # an earlier message, held till now

    def _aligned(self, msg, arrival_s: float, held: bool = False) -> None:
        if isinstance(msg, RobotState):
            self.aligner.pose(msg.stamp_s, arrival_s)
            self.kept["robot"] += 1
            self._deliver(msg)
        elif isinstance(msg, Profile):
            taken = time.monotonic()
            for p in self.aligner.profile(msg, arrival_s):
                self._arrivals[(p.sensor_id, p.stamp_s)] = (arrival_s, taken, held)
                if len(self._arrivals) > MAX_UNFUSED:  # dropped ones are never fused
                    self._arrivals.popitem(last=False)
                self._deliver(p)
        elif isinstance(msg, LayerMark):
            self._deliver(msg)
        else:
            self.analysis.extra_dropped["bad_message"] += 1

    def _deliver(self, msg) -> None:
        if self.recorder is not None:
            try:
                self.recorder.write(msg)
            except MessageError:
                self.analysis.extra_dropped["unrecordable_stamp"] += 1
                return
        self.analysis.feed(msg)
        if self.analysis.fusion.fused_log:
            self._note_fused()

    def _note_fused(self) -> None:
        now = time.monotonic()
        log_ = self.analysis.fusion.fused_log
        while log_:
            key = log_.popleft()
            self.kept[key[0]] += 1
            times = self._arrivals.pop(key, None)
            if times is not None:
                self.latencies_s.append(now - times[0])
                self.inbox_waits_s.append(times[1] - times[0])
                self.held_by_gates.append(times[2])

    def stream_shares(self) -> dict[str, dict]:
        """Each stream's messages received on its own connection, kept (robot states past the
        gates, profiles fused) and the share lost: ``{"robot"|"S1"|...: {...}}``."""
        kept = Counter(self.kept)
        for _ in range(10):  # fused but not tallied yet (read from any thread)
            try:
                kept.update(k[0] for k in list(self.analysis.fusion.fused_log))
                break
            except RuntimeError:
                continue
        out = {}
        for name, n in sorted(self.streams.received.items()):
            k = min(int(kept[name]), int(n))
            out[name] = {"received": int(n), "kept": k,
                         "lost_share": round(1.0 - k / n, 4) if n else 0.0}
        return out

    def stream_report(self) -> dict:
        """report.json's ``streams``: sources, duplicate sources, counters, per-stream loss."""
        return {**self.streams.report(), "per_stream": self.stream_shares()}

    def run(self, stop: threading.Event | None = None, max_duration_s: float | None = None,
            idle_stop_s: float | None = None) -> dict | None:
        """Process the inbox until ``stop`` is set, ``max_duration_s`` passed, or no data came
        for ``idle_stop_s`` after data started (0 or None: never); then :meth:`finish`."""
        live = self.cell.live
        max_duration_s = live.max_duration_s if max_duration_s is None else max_duration_s
        idle_stop_s = live.idle_stop_s if idle_stop_s is None else idle_stop_s
        monitor = self.analysis.fusion
        batch_delay_s, batch_profiles = monitor.max_delay_s, monitor.batch_profiles
        self._freeze_heap()
        t0 = time.monotonic()
        pending = False  # deferred session work left by the last catch-up

        def inbox_busy() -> bool:
            return self.inbox.qsize() > 0

        try:
            while not (stop is not None and stop.is_set()):
                now = time.monotonic()
                if max_duration_s is not None and now - t0 >= max_duration_s:
                    break
                idle = self._last_data is not None and now - self._last_data > idle_stop_s
                if idle_stop_s and idle:
                    log.info("no data for %.1f s: ending the run", idle_stop_s)
                    break
                if pending and not self.inbox.qsize():
                    t_idle = time.monotonic()
                    pending = not self.analysis.catch_up(inbox_busy)
                    self.busy_s += time.monotonic() - t_idle
                item = self.inbox.get(timeout_s=0.005 if pending else 0.05)
                if item is None:
                    continue
                self._last_data = time.monotonic()
                # caught up: a profile is fused as soon as it is ready (not held for its batch
                # while the loop catches up next); behind: profiles wait for a full batch or the
                # monitor's batch delay so fusion runs in efficient batches
                behind = self.inbox.qsize() > 0
                monitor.max_delay_s = batch_delay_s if behind else 0.0
                monitor.batch_profiles = batch_profiles if behind else 1
                self.process(*item)
                step = time.monotonic() - self._last_data
                self.busy_s += step
                self.max_step_s = max(self.max_step_s, step)
                pending = True
        finally:
            report = self.finish()
        return report

    def _freeze_heap(self) -> None:
        """Everything allocated so far (modules, compiled kernels, calibration, the reference
        grid: a few hundred thousand objects) leaves the cyclic collector's view until the run
        ends, so a full collection never stalls the stream for the 100+ ms it takes to scan
        them. Once per run, before the sources open (the collection itself takes that long)."""
        if not self._frozen:
            gc.collect()
            gc.freeze()
            self._frozen = True

    def _thaw_heap(self) -> None:
        if self._frozen:
            gc.unfreeze()
            self._frozen = False

    def drain(self) -> None:
        """Process everything already queued (no waiting)."""
        while (item := self.inbox.get(timeout_s=0)) is not None:
            self.process(*item)

    def finish(self) -> dict | None:
        """Close the sources, process what is queued, write the final report and recording."""
        if self._finished:
            return None
        self._finished = True
        for s in self.sources:
            s.close()
        self.drain()
        for m, arrival in self.gates.flush():
            self._aligned(m, arrival, held=True)
        for p in self.aligner.flush():
            self._deliver(p)
        fused = self.analysis.fusion.profiles_fused
        try:
            report = self.analysis.finish()
            self.fused_at_end = self.analysis.fusion.profiles_fused - fused
            log_ = self.analysis.fusion.fused_log
            while log_:
                self.kept[log_.popleft()[0]] += 1
        finally:
            self._thaw_heap()
            if self.recorder is not None:
                self.recorder.close()
        log.info("live run finished: %d messages, dropped %s", self.messages_in,
                 self.analysis.dropped)
        return report

    def close(self) -> None:
        """Release sockets and files without a final report (error paths)."""
        for s in self.sources:
            s.close()
        self._thaw_heap()
        if not self._finished:
            self.analysis.close()
            if self.recorder is not None:
                self.recorder.close(keep_part=True)
        self._finished = True
