"""``dm2 view RUN_FOLDER``: a finished run in the browser, layer by layer.

Reads the report folder (``RUN/report.json`` or ``RUN/report/report.json``): the per-layer
deviation PLYs (measured surface with ``scalar_signed_distance``, and the reference surface
through their ``ref_x ref_y ref_z`` points), the regions of every layer with their track ids,
and for twin runs the true surfaces in ``truth/layer_NNN.ply``. A layer slider chooses the
layer; a dropdown shows the measured, reference or true surface.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from dm2.view.scene import Scene, region_label

SURFACES = ("measured", "reference", "true")


def report_dir(run: str | Path) -> Path:
    """The folder holding report.json in a ``dm2 run`` or ``dm2 monitor`` output folder."""
    run = Path(run)
    for d in (run, run / "report"):
        if (d / "report.json").is_file():
            return d
    raise ValueError(f"{run}: no report.json here or in report/ (not a run folder)")


def read_layer_ply(path: Path) -> dict:
    """Vertices, faces and scalar fields of a report deviation PLY (triangles read at once,
    memory-mapped; any other face layout through dm2.io.ply.read_mesh_ply)."""
    from plyfile import PlyData

    from dm2.io.ply import read_mesh_ply

    try:
        ply = PlyData.read(str(path), known_list_len={"face": {"vertex_indices": 3}})
        vertex = ply["vertex"].data
        fields = {name: np.array(vertex[name]) for name in vertex.dtype.names}
        faces = np.array(ply["face"].data["vertex_indices"], dtype=np.int64).reshape(-1, 3)
    except (ValueError, KeyError, TypeError):
        fields, faces = read_mesh_ply(path)
    v = np.column_stack([fields["x"], fields["y"], fields["z"]]).astype(float)
    out = {"vertices": v, "faces": faces, "signed": fields["scalar_signed_distance"],
           "class": fields["scalar_class"]}
    if "ref_x" in fields:
        out["reference"] = np.column_stack([fields["ref_x"], fields["ref_y"], fields["ref_z"]])
    return out


class RunFolderView:
    """The GUI and scene of one finished run on a viser server."""

    def __init__(self, run: str | Path, server, limit_mm: float = 1.0):
        self.dir = report_dir(run)
        self.run = Path(run)
        self.report = json.loads((self.dir / "report.json").read_text(encoding="utf-8"))
        self.layers = {int(lay["layer"]): lay for lay in self.report.get("layers", [])}
        self.meshes = {int(Path(p).stem.split("_")[-1]): self.dir / p
                       for p in self.report.get("files", {}).get("meshes", [])
                       if (self.dir / p).is_file()}
        if not self.meshes:
            raise ValueError(f"{self.dir}: the report holds no layer meshes (meshes/*.ply)")
        truth = next((d for d in (self.run / "truth", self.dir / "truth") if d.is_dir()), None)
        self.truth = {} if truth is None else {
            int(p.stem.split("_")[-1]): p for p in truth.glob("layer_*.ply")}
        self.scene = Scene(server, limit_mm)
        self.server = server
        keys = sorted(self.meshes)
        gui = server.gui
        self.info = gui.add_markdown("")
        self.slider = gui.add_slider("layer", min=keys[0], max=keys[-1], step=1,
                                     initial_value=keys[-1])
        options = [s for s in SURFACES if s != "true" or self.truth]
        self.surface = gui.add_dropdown("surface", options, initial_value="measured")
        self.slider.on_update(lambda _: self.show())
        self.surface.on_update(lambda _: self.show())
        self.show()

    def show(self) -> None:
        layer = int(self.slider.value)
        if layer not in self.meshes:
            layer = min(self.meshes, key=lambda k: abs(k - layer))
        what = self.surface.value
        data = read_layer_ply(self.meshes[layer])
        if what == "measured":
            self.scene.surface("/surface", data["vertices"], data["faces"], data["signed"],
                               data["class"].astype(np.int8))
        elif what == "reference" and "reference" in data:
            self.scene.surface("/surface", data["reference"], data["faces"],
                               rgb=(200, 200, 200))
        elif what == "true" and layer in self.truth:
            import trimesh

            mesh = trimesh.load(self.truth[layer], process=False, force="mesh")
            self.scene.surface("/surface", mesh.vertices, mesh.faces, rgb=(214, 196, 160))
        regions = self.layers.get(layer, {}).get("regions", [])
        self.scene.tracks([(r.get("track_id"), r["kind"], r["bbox_min_O_mm"], r["bbox_max_O_mm"])
                           for r in regions])
        found = ", ".join(f"{region_label(r.get('track_id'), r['kind'])} "
                          f"{r['area_mm2']:.0f} mm²" for r in regions[:8]) or "no regions"
        self.info.content = (f"**Layer {layer}** of {len(self.meshes)} · {what} surface · "
                             f"colour: signed deviation ±{self.scene.limit_mm:g} mm (blue "
                             f"under, red over)\n\n{found}")
