"""The live 3D view of a running session (``dm2 run --view``, ``dm2 monitor --view``).

The session hands each analysed layer to :meth:`LiveView.on_layer` (from the layer worker, or
inline where the session has none): it only keeps a reference to the newest result and
returns. A daemon thread of its own, at most :data:`UPDATE_HZ` times per second, sends the
newest layer's surface, its tracks and the current layer, and the nozzle and sensor frames at
the latest robot pose (read from ``pose_source``, a cheap attribute read), to a child process
(:mod:`dm2.view.view_child`) that serves them to the browser: the surface coloured by signed
deviation with the maps' colour scale, the tracks as labelled boxes. Encoding the scene and
serving the websocket run there, so the view never holds this process's interpreter lock for
longer than it takes to pickle one layer's arrays; nothing runs on the fusion path.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable

import numpy as np

from dm2.core.frames import invert
from dm2.io.child_process import ChildError, PickleChild

log = logging.getLogger(__name__)

UPDATE_HZ = 3.0  # scene updates per second at most


class LiveView:
    """Serve the growing part on ``host:port`` (from a child process, started here: the
    constructor returns once it serves, :attr:`url` its address); call :meth:`close` at the
    end of the stream and :meth:`stop_server` when the view is no longer wanted.

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
        self._child = PickleChild("dm2.view.view_child", (host, str(int(port)), repr(limit_mm)),
                                  what="3D view").start()
        self.url = self._child.ready_value
        self._pending = None
        self._shown = None
        self._stop = threading.Event()
        self.updates = 0
        self._thread = threading.Thread(target=self._loop, name="live-view", daemon=True)
        self._thread.start()

    def on_layer(self, result) -> None:
        """A layer was analysed (any thread): keep it for the next scene update."""
        self._pending = result

    def state(self) -> dict:
        """What the view shows: ``status`` (its status line), ``poses`` (frame name -> T_O_X
        [mm]), ``updates`` (layers shown), ``clients`` (browsers connected)."""
        return self._child.request(("state", None))

    def _loop(self) -> None:
        period = 1.0 / UPDATE_HZ
        while not self._stop.wait(period):
            try:
                self._update()
            except ChildError as exc:
                log.warning("live view: %s; the view stops, the run goes on", exc)
                return
            except Exception:  # noqa: BLE001 - the view never stops the run
                log.exception("live view: update failed")

    def _update(self) -> None:
        res = self._pending
        if res is not None and res is not self._shown:
            self._child.request(("layer", layer_payload(res)))
            self._shown = res
            self.updates += 1
        T_B_F = self.pose_source() if self.pose_source is not None else None
        if T_B_F is not None:
            cal = self.calibration
            T_O_B = invert(np.asarray(T_B_F) @ cal.T_F_O)
            poses = {"nozzle": T_O_B @ cal.T_B_N}
            poses.update({sid: T_O_B @ T for sid, T in cal.T_B_S.items()})
            self._child.request(("poses", poses))

    def close(self) -> None:
        """The stream ended: stop the updates and show the final layer (the view keeps
        serving until :meth:`stop_server`)."""
        self._stop.set()
        self._thread.join(timeout=5)
        if not self._child.alive:
            return
        try:
            self._update()
        except Exception:  # noqa: BLE001 - the view never stops the run
            log.exception("live view: last update failed")

    def stop_server(self) -> None:
        self._stop.set()
        self._child.close()


def layer_payload(result) -> dict:
    """What the view child needs of a dm2.defects.LayerResult: its surface (float32 vertices
    [mm] in O, int32 faces, signed deviation [mm], class codes) and its regions as boxes
    (track id None: a region no track holds)."""
    dev = result.deviation
    return {"layer": int(result.layer),
            "vertices_O_mm": np.asarray(dev.vertices_O, np.float32),
            "faces": np.asarray(dev.faces, np.int32),
            "signed_mm": np.asarray(dev.signed_distance_mm, np.float32),
            "class_code": np.asarray(dev.class_code, np.int8),
            "boxes": [(None if tid is None else int(tid), r.kind, np.asarray(r.bbox_min_O, float),
                       np.asarray(r.bbox_max_O, float))
                      for r, tid in zip(result.regions, result.track_ids, strict=True)]}


def serve_forever(stop: threading.Event | None = None) -> None:
    """Block until Ctrl-C (or ``stop``)."""
    stop = stop or threading.Event()
    try:
        while not stop.wait(0.5):
            pass
    except KeyboardInterrupt:
        pass

