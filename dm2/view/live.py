"""The live 3D view of a running session (``dm2 run --view``, ``dm2 monitor --view``).

The session hands each analysed layer to :meth:`LiveView.on_layer` (from the layer worker, or
inline where the session has none): it only keeps a reference to the newest result and
returns. A daemon thread of its own, at most :data:`UPDATE_HZ` times per second, sends the
newest layer's surface (coloured by signed deviation, the maps' colour scale), its tracks as
labelled boxes, the current layer, and the nozzle and sensor frames at the latest robot pose
(read from ``pose_source``, a cheap attribute read) to the browser. Nothing here runs on the
fusion path.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable

import numpy as np

from dm2.core.frames import invert
from dm2.view.scene import Scene, start_server, url_of

log = logging.getLogger(__name__)

UPDATE_HZ = 3.0  # scene updates per second at most


class LiveView:
    """Serve the growing part on ``host:port``; call :meth:`close` at the end.

    Parameters
    ----------
    calibration : dm2.core.messages.Calibration (``T_F_O``, ``T_B_N``, ``T_B_S``)
    pose_source : callable returning the latest ``T_B_F`` (4, 4) or None
    limit_mm : colour range of the signed deviation [mm]
    """

    def __init__(self, calibration, pose_source: Callable[[], np.ndarray | None] | None = None,
                 limit_mm: float = 1.0, host: str = "127.0.0.1", port: int = 8080):
        self.calibration = calibration
        self.pose_source = pose_source
        self.server = start_server(host, port)
        self.url = url_of(self.server)
        self.scene = Scene(self.server, limit_mm)
        self.status = self.server.gui.add_markdown("waiting for the first layer")
        self._pending = None
        self._shown = None
        self._stop = threading.Event()
        self._frames: dict = {}
        self.updates = 0
        self._warm_up()
        self._thread = threading.Thread(target=self._loop, name="live-view", daemon=True)
        self._thread.start()

    def _warm_up(self) -> None:
        """Load the mesh encoding and colour code once now (about 2 s the first time), before
        any stream arrives, instead of at the first layer."""
        v = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
        handle = self.scene.surface("/warm_up", v, np.array([[0, 1, 2]]), np.zeros(3))
        handle.remove()
        self.scene._camera_set = False

    def on_layer(self, result) -> None:
        """A layer was analysed (any thread): keep it for the next scene update."""
        self._pending = result

    def _loop(self) -> None:
        period = 1.0 / UPDATE_HZ
        while not self._stop.wait(period):
            try:
                self._update()
            except Exception:  # noqa: BLE001 - the view never stops the run
                log.exception("live view: update failed")

    def _update(self) -> None:
        res = self._pending
        if res is not None and res is not self._shown:
            dev = res.deviation
            self.scene.surface_chunked("/surface", dev.vertices_O, dev.faces,
                                       dev.signed_distance_mm, dev.class_code)
            self.scene.tracks([(tid, r.kind, r.bbox_min_O, r.bbox_max_O)
                               for r, tid in zip(res.regions, res.track_ids, strict=True)])
            self.status.content = (f"**Layer {res.layer}** analysed · {len(res.regions)} "
                                   f"region(s) · colour: signed deviation "
                                   f"±{self.scene.limit_mm:g} mm")
            self._shown = res
            self.updates += 1
        T_B_F = self.pose_source() if self.pose_source is not None else None
        if T_B_F is not None:
            cal = self.calibration
            T_O_B = invert(np.asarray(T_B_F) @ cal.T_F_O)
            poses = {"nozzle": T_O_B @ cal.T_B_N}
            poses.update({sid: T_O_B @ T for sid, T in cal.T_B_S.items()})
            for name, T in poses.items():
                if name in self._frames:
                    from dm2.view.scene import MM, quat_wxyz

                    self._frames[name].position = tuple(T[:3, 3] * MM)
                    self._frames[name].wxyz = tuple(quat_wxyz(T))
                else:
                    self._frames[name] = self.scene.frame(f"/frames/{name}", T, label=name)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        try:
            self._update()  # the final layer
        except Exception:  # noqa: BLE001
            log.exception("live view: last update failed")

    def stop_server(self) -> None:
        self.server.stop()


def serve_forever(stop: threading.Event | None = None) -> None:
    """Block until Ctrl-C (or ``stop``)."""
    stop = stop or threading.Event()
    try:
        while not stop.wait(0.5):
            pass
    except KeyboardInterrupt:
        pass

