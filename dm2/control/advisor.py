"""After each analysed layer, the next layer corrected: kept for the report and written as a
RAPID module and a toolpath CSV (``--compensate advise``: for a human to load)."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from dm2.control.law import LayerCorrection, correct_layer
from dm2.control.top_map import measured_top
from dm2.core.config import ControlConfig
from dm2.core.messages import Toolpath

log = logging.getLogger(__name__)

TOP_MARGIN_MM = 5.0  # the measured top is mapped this far around the next layer's path


def layer_file_stem(layer: int) -> str:
    return f"layer_{layer:04d}"


class Compensator:
    """The closed loop's state over a build.

    toolpath : the programmed toolpath (the design intent: its target heights per layer)
    cfg : the ``[control]`` settings; layer_mm : the planned layer height [mm]
    out_dir : where each corrected layer's ``layer_NNNN.mod`` and ``layer_NNNN.csv`` go (None:
        nothing written)
    """

    def __init__(self, toolpath: Toolpath, cfg: ControlConfig, layer_mm: float,
                 out_dir: str | Path | None = None):
        self.programmed = toolpath
        self.toolpath = toolpath  # the programmed one with every correction so far
        self.cfg = cfg
        self.layer_mm = float(layer_mm)
        self.out_dir = None if out_dir is None else Path(out_dir)
        self.corrections: dict[int, LayerCorrection] = {}
        self.compute_s: list[float] = []

    def on_layer(self, result) -> None:
        """Layer ``result.layer`` analysed (a :class:`dm2.defects.layer_analysis.LayerResult`):
        correct the next one."""
        dev = result.deviation
        verts = dev.vertices_O
        if dev.unseen_mm is not None:  # grown since the profilers last saw it: as modelled
            verts = verts.copy()
            verts[:, 2] += np.nan_to_num(dev.unseen_mm)
        self.correct_next(int(result.layer), verts, dev.normals_O, dev.weight)

    def correct_next(self, layer: int, vertices_O, normals_O=None, weight=None
                     ) -> LayerCorrection | None:
        """The correction of layer ``layer + 1`` from the top measured after ``layer``."""
        import time

        nxt = layer + 1
        rows = self.toolpath.layer == nxt
        if not rows.any():
            return None
        t0 = time.perf_counter()
        xy = self.toolpath.position_O[rows, :2]
        lo, hi = xy.min(axis=0) - TOP_MARGIN_MM, xy.max(axis=0) + TOP_MARGIN_MM
        top = measured_top(vertices_O, normals_O, weight, self.cfg.top_cell_mm,
                           self.cfg.min_weight, bounds_O=(*lo, *hi))
        self.toolpath, corr = correct_layer(self.toolpath, nxt, top, self.cfg, self.layer_mm,
                                            previous=self.corrections.get(layer))
        self.compute_s.append(time.perf_counter() - t0)
        self.corrections[nxt] = corr
        if self.out_dir is not None:
            self._write(nxt)
        s = corr.summary()
        log.info("control: layer %d speed factor %.2f..%.2f (mean %.2f)", nxt,
                 s["min_factor"], s["max_factor"], s["mean_factor"])
        return corr

    def layer_toolpath(self, layer: int) -> Toolpath:
        """Layer ``layer`` alone, with its corrected speeds."""
        return self.toolpath.select(self.toolpath.layer == layer)

    def _write(self, layer: int) -> None:
        from dm2.toolpath.formats import write_csv, write_rapid

        self.out_dir.mkdir(parents=True, exist_ok=True)
        tp = self.layer_toolpath(layer)
        stem = layer_file_stem(layer)
        write_rapid(tp, self.out_dir / f"{stem}.mod", module_name=f"DM2_Layer_{layer:04d}")
        write_csv(tp, self.out_dir / f"{stem}.csv")

    def summary(self, mode: str) -> dict:
        """The ``control`` section of ``report.json``."""
        t = np.asarray(self.compute_s)
        return {"mode": mode, "config": self.cfg.model_dump(), "layer_mm": self.layer_mm,
                "files": None if self.out_dir is None else self.out_dir.name,
                "compute_s_max": float(t.max()) if t.size else 0.0,
                "layers": [c.summary() for _, c in sorted(self.corrections.items())]}
