"""The live scene over Foxglove's WebSocket protocol (``dm2 run --foxglove``,
``dm2 monitor --live ... --foxglove``).

The same channels as a run's ``scene.mcap`` (:mod:`dm2.report.scene_mcap`), served by
foxglove-sdk's server while the part grows. The session hands each analysed layer to
:meth:`FoxgloveLive.on_layer` (from the layer worker, or inline where there is none), which
only keeps a reference to it. A daemon thread of its own, at most :data:`UPDATE_HZ` times per
second, sends the newest layer (surface, reference, tracks, plot rows), the frames at the
newest robot pose and the real-time alarms raised since its last update; it sends the newest
layer again every :data:`RESEND_S` so that a client connecting mid-run sees the part. The
server's sockets run on the SDK's own threads, outside the interpreter lock; nothing runs on
the fusion path. Messages carry the run's stamps; their log time is the host's.
"""

from __future__ import annotations

import ipaddress
import logging
import threading
import time

import foxglove

from dm2.report import scene_messages as sm
from dm2.report.scene_mcap import SceneChannels

log = logging.getLogger(__name__)

UPDATE_HZ = 3.0  # scene updates per second at most
RESEND_S = 2.0  # the newest layer again after this long, for clients that joined later


def check_host(host: str, allow_remote: bool) -> str:
    """``host`` when it is a loopback address or ``allow_remote`` is set; else ValueError
    naming it (the server would expose the cell's data to the network)."""
    try:
        loopback = host == "localhost" or ipaddress.ip_address(host).is_loopback
    except ValueError:
        loopback = False
    if not loopback and not allow_remote:
        raise ValueError(f"--foxglove-host: {host!r} is not a loopback address; set "
                         "allow_remote to serve the scene to other machines")
    return host


class FoxgloveLive:
    """Serve the growing part on ``host:port``; :attr:`url` its address (``ws://host:port``),
    :meth:`attach` the pipeline it follows, :meth:`close` at the end (sends the last layer,
    stops the updates); :meth:`stop_server` stops serving.

    Parameters
    ----------
    calibration : dm2.core.messages.Calibration (``T_F_O``, ``T_B_N``, ``T_B_S``)
    pipeline : the dm2.pipeline.pipeline.Pipeline being run, or None until :meth:`attach`
        (its newest robot pose and real-time alarms are read, never written)
    limit_mm : colour range of the signed deviation [mm]
    """

    def __init__(self, calibration, pipeline=None, host: str = "127.0.0.1", port: int = 8765,
                 allow_remote: bool = False, limit_mm: float = 1.0):
        self.calibration = calibration
        self.limit_mm = float(limit_mm)
        self.channels = SceneChannels()
        try:
            self.server = foxglove.start_server(name="dm2", host=check_host(host, allow_remote),
                                                port=int(port), context=self.channels.context)
        except RuntimeError as exc:  # the SDK's FoxgloveError: the port is taken, ...
            raise ValueError(f"Foxglove server on {host}:{port}: {exc}") from exc
        self.url = f"ws://{host}:{self.server.port}"
        self._lock = threading.Lock()
        self.attach(pipeline)
        self._stop = threading.Event()
        self.updates = 0
        self._thread = threading.Thread(target=self._loop, name="foxglove-live", daemon=True)
        self._thread.start()

    def attach(self, pipeline) -> None:
        """Follow ``pipeline`` from now on (a new run on the same server)."""
        with self._lock:
            self.pipeline = pipeline
            self._pending = self._sent = None
            self._sent_at = 0.0
            self._alarms_sent = 0
            self._stamp_s = 0.0

    def on_layer(self, result) -> None:
        """A layer was analysed (any thread): keep it for the next update."""
        self._pending = result

    def _loop(self) -> None:
        period = 1.0 / UPDATE_HZ
        while not self._stop.wait(period):
            try:
                self.update()
            except Exception:  # noqa: BLE001 - the live scene never stops the run
                log.exception("foxglove: update failed")

    def update(self) -> None:
        """One scene update (see the module docstring)."""
        with self._lock:
            items = []
            res = self._pending
            now = time.monotonic()
            if res is not None and (res is not self._sent or now - self._sent_at >= RESEND_S):
                items.extend(sm.layer_messages(res, self.limit_mm))
                self._stamp_s = max(self._stamp_s, float(res.deviation.stamp_s))
                self._sent, self._sent_at = res, now
                self.updates += 1
            alarms = [] if self.pipeline is None else list(self.pipeline.session.realtime.alarms)
            for k in range(self._alarms_sent, len(alarms)):
                a = alarms[k]
                alarm = {"stamp_s": a.stamp_s, "kind": a.kind, "area_mm2": a.area_mm2,
                         "centroid_xy_O_mm": [float(c) for c in a.centroid_xy_O],
                         "delay_s": a.stamp_s - a.first_flag_s}
                top = float(res.deviation.vertices_O[:, 2].max()) \
                    if res is not None and res.deviation.n_vertices else 0.0
                items.extend(sm.alarm_messages(k, alarm, top))
                self._stamp_s = max(self._stamp_s, float(a.stamp_s))
            self._alarms_sent = len(alarms)
            pose = None if self.pipeline is None else self.pipeline.last_T_B_F
            items.append(sm.frame_messages(self._stamp_s, self.calibration, pose))
            self.channels.log(items, log_time=False)

    def send_findings(self, report: dict) -> None:
        """The verdict and process findings of the finished run."""
        with self._lock:
            self.channels.log(sm.finding_messages(self._stamp_s, report), log_time=False)

    def close(self) -> None:
        """End of stream: one last update, then no more (the server goes on serving)."""
        if self._stop.is_set():
            return
        self._stop.set()
        self._thread.join(timeout=5.0)
        try:
            self.update()
        except Exception:  # noqa: BLE001
            log.exception("foxglove: last update failed")

    def stop_server(self) -> None:
        self.close()
        self.server.stop()
