"""The child process that serves the live 3D view (``python -m dm2.view.view_child HOST PORT
LIMIT_MM``), so encoding and sending the scene never holds the fusion process's interpreter
lock.

It runs the viser server and applies what :class:`dm2.view.live.LiveView` sends over its pipe
(:mod:`dm2.io.child_process`): ``("layer", payload)`` replaces the surface, the track boxes and
the status line; ``("poses", {name: T_O_X})`` places the nozzle and sensor frames;
``("state", None)`` answers what is shown (the status line, the frames' poses, the number of
layers shown and of connected browsers). Its ready answer is the view's URL.
"""

from __future__ import annotations

import os
import sys

import numpy as np

from dm2.io.child_process import serve
from dm2.view.scene import MM, Scene, quat_wxyz, start_server, url_of


class ViewScene:
    """The scene a live view shows, updated by requests (see the module docstring)."""

    def __init__(self, host: str, port: int, limit_mm: float):
        self.server = start_server(host, port)
        self.url = url_of(self.server)
        self.scene = Scene(self.server, limit_mm)
        self.status = self.server.gui.add_markdown("waiting for the first layer")
        self.frames: dict = {}
        self.poses: dict[str, np.ndarray] = {}
        self.updates = 0
        self._warm_up()

    def _warm_up(self) -> None:
        """Load the mesh encoding and colour code once now (about 2 s the first time), before
        any stream arrives, instead of at the first layer."""
        v = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
        handle = self.scene.surface("/warm_up", v, np.array([[0, 1, 2]]), np.zeros(3))
        handle.remove()
        self.scene._camera_set = False

    def handle(self, request):
        kind, body = request
        if kind == "layer":
            return self.layer(body)
        if kind == "poses":
            return self.place(body)
        if kind == "state":
            return {"status": self.status.content, "updates": self.updates,
                    "poses": {k: T.copy() for k, T in self.poses.items()},
                    "clients": len(self.server.get_clients())}
        raise ValueError(f"unknown request {kind!r}")

    def layer(self, p: dict) -> None:
        self.scene.surface_chunked("/surface", p["vertices_O_mm"], p["faces"], p["signed_mm"],
                                   p["class_code"])
        self.scene.tracks(p["boxes"])
        self.status.content = (f"**Layer {p['layer']}** analysed · {len(p['boxes'])} "
                               f"region(s) · colour: signed deviation "
                               f"±{self.scene.limit_mm:g} mm")
        self.updates += 1

    def place(self, poses: dict) -> None:
        for name, T in poses.items():
            T = np.asarray(T, float)
            if name in self.frames:
                self.frames[name].position = tuple(T[:3, 3] * MM)
                self.frames[name].wxyz = tuple(quat_wxyz(T))
            else:
                self.frames[name] = self.scene.frame(f"/frames/{name}", T, label=name)
            self.poses[name] = T


if __name__ == "__main__":
    shown: list[ViewScene] = []

    def _start():
        host, port, limit_mm = sys.argv[1], int(sys.argv[2]), float(sys.argv[3])
        sys.stdout = open(os.devnull, "w")  # viser prints status lines; the child only logs
        shown.append(ViewScene(host, port, limit_mm))
        return shown[0].handle, shown[0].url

    serve("3D view", _start)
    if shown:
        shown[0].server.stop()
