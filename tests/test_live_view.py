"""The live 3D view: the newest layer is shown, the nozzle and sensor frames sit where the
calibration and the robot pose put them in O, and on_layer only keeps the result."""

from __future__ import annotations

import numpy as np
from chromium import free_port

from dm2.core.messages import Calibration
from dm2.report.synthetic import synthetic_run
from dm2.view.live import LiveView
from dm2.view.scene import MM


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
        for r in results:
            view.on_layer(r)  # only the newest counts
        assert view._pending is results[-1] and view.updates == 0
        view._update()
        view._update()  # nothing new: no second scene update
        assert view.updates == 1 and view._shown is results[-1]
        assert "Layer 2" in view.status.content
        T_O_B = np.linalg.inv(T_B_F @ cal.T_F_O)
        for name, T_B_X in [("nozzle", cal.T_B_N)] + sorted(cal.T_B_S.items()):
            frame = view._frames[name]
            np.testing.assert_allclose(np.asarray(frame.position) / MM, (T_O_B @ T_B_X)[:3, 3],
                                       atol=1e-6)
    finally:
        view.stop_server()
