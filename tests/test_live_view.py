"""The live 3D view: the newest layer is shown, the nozzle and sensor frames sit where the
calibration and the robot pose put them in O, on_layer only keeps the result, and the scene
is served by a child process (the fusion process only pickles the layer's arrays)."""

from __future__ import annotations

import numpy as np
import pytest
from chromium import free_port

from dm2.core.messages import Calibration
from dm2.io.child_process import ChildError
from dm2.report.synthetic import synthetic_run
from dm2.view.live import LiveView


def _pose(t_mm, yaw):
    c, s = np.cos(yaw), np.sin(yaw)
    T = np.eye(4)
    T[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    T[:3, 3] = t_mm
    return T


def test_live_view_shows_the_newest_layer_and_places_the_frames():
    cal = Calibration(T_B_S={f"S{k}": _pose([100.0 * k, 20.0, 900.0], 0.3 * k) for k in (1, 2, 3)},
                      T_F_O=_pose([-60.0, -60.0, 50.0], 0.0), T_B_N=_pose([1200.0, 0.0, 800.0],
                                                                            0.0))
    T_B_F = _pose([1200.0, 30.0, 700.0], 0.5)
    view = LiveView(cal, pose_source=lambda: T_B_F, port=free_port())
    try:
        results, _, _ = synthetic_run(n_layers=3, n_tracks=6, size_mm=20.0)
        view._stop.set()  # drive the updates by hand
        view._thread.join()
        results[-1].track_ids[0] = None  # a region no track holds gets a box of its own
        for r in results:
            view.on_layer(r)  # only the newest counts
        assert view._pending is results[-1] and view.updates == 0
        view._update()
        view._update()  # nothing new: no second scene update
        assert view.updates == 1 and view._shown is results[-1]
        state = view.state()
        assert state["updates"] == 1 and state["clients"] == 0
        assert state["status"].startswith("**Layer 2** analysed")
        assert f"{len(results[-1].regions)} region(s)" in state["status"]
        T_O_B = np.linalg.inv(T_B_F @ cal.T_F_O)
        names = ["nozzle", *sorted(cal.T_B_S)]
        assert sorted(state["poses"]) == sorted(names)
        for name, T_B_X in [("nozzle", cal.T_B_N)] + sorted(cal.T_B_S.items()):
            np.testing.assert_allclose(state["poses"][name], T_O_B @ T_B_X, atol=1e-9)
        child = view._child.proc
    finally:
        view.stop_server()
    assert child.poll() is not None  # the child ended with the view


def test_live_view_names_the_reason_it_cannot_start():
    with pytest.raises(ChildError, match="3D view did not start: ValueError: port 70000"):
        LiveView(Calibration(T_B_S={}, T_F_O=np.eye(4), T_B_N=np.eye(4)), port=70000)
    with pytest.raises(ChildError, match="3D view did not start: ValueError: host '192.0.2.1'"):
        LiveView(Calibration(T_B_S={}, T_F_O=np.eye(4), T_B_N=np.eye(4)), host="192.0.2.1",
                 port=free_port())


def test_live_view_keeps_the_console_quiet_for_unused_browser_connections(capfd):
    """A browser's spare connection, opened and closed unused, logs nothing, and viser's
    banner is not printed: the engineer's console shows only what the monitor says."""
    import socket
    import time

    port = free_port()
    view = LiveView(Calibration(T_B_S={}, T_F_O=np.eye(4), T_B_N=np.eye(4)), port=port)
    try:
        for _ in range(3):
            socket.create_connection(("127.0.0.1", port), timeout=5).close()
        time.sleep(1.0)  # the server notices the closed connections
        assert view.state()["clients"] == 0  # the child still answers
    finally:
        view.stop_server()
    err = capfd.readouterr()
    text = err.out + err.err
    assert "handshake" not in text and "Traceback" not in text and "viser" not in text


def test_unused_connection_filter_keeps_other_handshake_failures():
    import logging

    from dm2.view.scene import UnusedConnections

    def record(exc):
        try:
            raise exc
        except Exception as caught:  # noqa: BLE001
            info = (type(caught), caught, caught.__traceback__)
        return logging.LogRecord("websockets.server", logging.ERROR, __file__, 1,
                                 "opening handshake failed", None, info)

    closed = ValueError("did not receive a valid HTTP request")
    closed.__cause__ = EOFError("connection closed while reading HTTP request line")
    f = UnusedConnections()
    assert not f.filter(record(closed))  # closed before a request: dropped
    assert f.filter(record(ValueError("invalid Sec-WebSocket-Key")))  # a real failure: kept
