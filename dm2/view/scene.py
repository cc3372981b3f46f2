"""The 3D scene of a run in the browser (viser): surfaces coloured by signed deviation with the
report maps' colour scale, tracks as labelled boxes, the nozzle and sensor frames.

Scene units are metres (viser's camera and grid expect them); every input here is in
millimetres in the work-object frame ``O``.
"""

from __future__ import annotations

import logging

import numpy as np

from dm2.report.meshes import deviation_colours

MM = 1e-3  # scene units per mm
MAX_BOXES = 30  # track boxes shown per layer at most (the largest regions come first)
BOX_RGB = {"overbuild": (178, 24, 43), "underbuild": (33, 102, 172),
           "local_overbuild": (244, 165, 130), "local_underbuild": (146, 197, 222)}


class UnusedConnections(logging.Filter):
    """Drop websockets' "opening handshake failed" error for a connection that closed before
    it sent a request: browsers open spare connections ahead and close them unused (Chromium
    does at every page load), and each one printed a traceback on the engineer's console. A
    handshake that fails on what the client did send is still logged."""

    def filter(self, record: logging.LogRecord) -> bool:
        if record.getMessage() != "opening handshake failed" or not record.exc_info:
            return True
        exc = record.exc_info[1]
        while exc is not None:
            if isinstance(exc, EOFError):
                return False
            exc = exc.__cause__
        return True


def start_server(host: str = "127.0.0.1", port: int = 8080):
    """A viser server on ``host:port`` (port 0 is not supported: pick a free one; a port in
    use is skipped for the next free one). Raises ValueError for a port outside 1-65535 or a
    host this machine cannot serve on (viser would retry those forever). viser's own banner
    is not printed (the caller prints the URL), nor are browsers' unused connections logged
    (:class:`UnusedConnections`)."""
    import contextlib
    import io
    import socket

    import viser

    if not 1 <= int(port) <= 65535:
        raise ValueError(f"port {port}: not in 1-65535")
    try:
        family, kind, _, _, address = socket.getaddrinfo(host, 0, type=socket.SOCK_STREAM)[0]
        with socket.socket(family, kind) as s:
            s.bind(address)
    except OSError as exc:
        raise ValueError(f"host {host!r}: cannot serve there ({exc})") from None

    server_log = logging.getLogger("websockets.server")
    if not any(isinstance(f, UnusedConnections) for f in server_log.filters):
        server_log.addFilter(UnusedConnections())
    with contextlib.redirect_stdout(io.StringIO()):  # viser prints a banner even when quiet
        server = viser.ViserServer(host=host, port=port, verbose=False)
    server.scene.set_up_direction("+z")
    return server


def url_of(server) -> str:
    return f"http://{server.get_host()}:{server.get_port()}"


def quat_wxyz(T: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(T[:3, :3]).as_quat()
    return np.array([w, x, y, z])


class Scene:
    """Named nodes of one viser server, replaced in place on every update."""

    def __init__(self, server, limit_mm: float = 1.0):
        self.server = server
        self.limit_mm = float(limit_mm)
        self._boxes: list = []
        self._chunks: dict[str, list] = {}
        self._camera_set = False

    def surface_chunked(self, name: str, vertices_O_mm, faces, signed_mm, class_code,
                        chunk_faces: int = 12_000) -> None:
        """:meth:`surface` sent as several meshes of at most ``chunk_faces`` faces (the browser
        takes them one by one); the chunks of the previous call under ``name`` are replaced."""
        faces = np.asarray(faces)
        n = max(int(np.ceil(len(faces) / chunk_faces)), 1)
        handles = []
        for k in range(n):
            f = faces[k * chunk_faces:(k + 1) * chunk_faces]
            used, inverse = np.unique(f, return_inverse=True)
            handles.append(self.surface(f"{name}/{k}", np.asarray(vertices_O_mm)[used],
                                        inverse.reshape(-1, 3), np.asarray(signed_mm)[used],
                                        np.asarray(class_code)[used]))
        for h in self._chunks.get(name, [])[n:]:
            h.remove()
        self._chunks[name] = handles

    def surface(self, name: str, vertices_O_mm, faces, signed_mm=None, class_code=None,
                rgb=None, visible: bool = True):
        """A mesh coloured by signed deviation (``signed_mm``), or plain ``rgb``."""
        import trimesh

        v = np.asarray(vertices_O_mm, np.float64)
        if signed_mm is not None:
            code = np.zeros(len(v), np.int8) if class_code is None else class_code
            colours = deviation_colours(np.asarray(signed_mm, float), np.asarray(code),
                                        self.limit_mm)
        else:
            colours = np.tile(np.asarray(rgb or (180, 180, 180), np.uint8), (len(v), 1))
        mesh = trimesh.Trimesh(v * MM, np.asarray(faces), vertex_colors=colours, process=False)
        handle = self.server.scene.add_mesh_trimesh(name, mesh, visible=visible)
        if not self._camera_set and len(v):
            self._aim(v)
        return handle

    def _aim(self, v_mm: np.ndarray) -> None:
        centre = np.median(v_mm, axis=0) * MM
        span = float(np.ptp(v_mm[:, :2], axis=0).max()) * MM if len(v_mm) > 1 else 0.05
        cam = self.server.initial_camera
        cam.look_at = tuple(centre)
        cam.position = tuple(centre + np.array([0.9, -1.2, 1.1]) * max(span, 0.03))
        self._camera_set = True

    def tracks(self, boxes) -> None:
        """``boxes`` = ``[(track_id, kind, bbox_min_O_mm, bbox_max_O_mm), ...]``: wireframe
        boxes; a track's carries its number and kind above it, always shown. A region no track
        holds (track_id None: an early warning, or not yet persistent) is named by what it is
        ("untracked local overbuild") only while its box is clicked, so a dozen small regions
        at a top do not bury the tracks' labels. Earlier boxes are removed."""
        for h in self._boxes:
            h.remove()
        self._boxes = []
        for k, (tid, kind, lo, hi) in enumerate(list(boxes)[:MAX_BOXES]):
            lo, hi = np.asarray(lo, float), np.asarray(hi, float)
            name = f"/tracks/{tid}" if tid is not None else f"/regions/{k}"
            text = region_label(tid, kind)
            dims = np.maximum(hi - lo, 0.2) * MM
            centre = (lo + hi) / 2 * MM
            rgb = BOX_RGB.get(kind, (0, 0, 0))
            box = self.server.scene.add_box(name, color=rgb, dimensions=tuple(dims),
                                            position=tuple(centre), wireframe=True)
            label = self.server.scene.add_label(
                f"{name}_label", text, position=(centre[0], centre[1], hi[2] * MM + 0.002),
                visible=tid is not None)
            if tid is None:
                box.on_click(lambda _event, label=label: setattr(label, "visible",
                                                                 not label.visible))
            self._boxes += [box, label]

    def frame(self, name: str, T_O_X: np.ndarray, label: str | None = None,
              length_mm: float = 12.0):
        """A coordinate frame at pose ``T_O_X`` [mm]."""
        pos = T_O_X[:3, 3] * MM
        handle = self.server.scene.add_frame(name, axes_length=length_mm * MM,
                                             axes_radius=0.4 * MM, wxyz=quat_wxyz(T_O_X),
                                             position=tuple(pos))
        if label:
            self.server.scene.add_label(f"{name}/label", label, position=(0.0, 0.0, 0.004))
        return handle


def region_label(track_id: int | None, kind: str) -> str:
    """What a region's box is called: ``"#3 overbuild"`` for a track's, ``"untracked local
    overbuild"`` for a region no track holds."""
    what = kind.replace("_", " ")
    return f"#{track_id} {what}" if track_id is not None else f"untracked {what}"
