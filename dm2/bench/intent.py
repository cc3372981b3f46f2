"""A part's top scored against the design intent (the closed loop's bench).

The intent after layer ``L`` is the toolpath's planned top: the height layer ``L + 1`` is
programmed to spray onto (``(L + 1) * layer_mm`` on a flat part), over the cells within half a
line spacing of layer ``L``'s spraying infill, less ``EDGE_MM`` from that footprint's border
(the flanks' Gaussian shoulders are not the top). A top is the highest surface point per
``CELL_MM`` cell.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import binary_erosion
from scipy.spatial import cKDTree

from dm2.core.messages import KIND_CODE, Toolpath

CELL_MM = 0.5
EDGE_MM = 2.0


def intent_footprint(toolpath: Toolpath, layer: int, spacing_mm: float, origin_O, shape):
    """(ny, nx) bool: the cells of the grid (``origin_O``, ``CELL_MM``) the layer's infill
    covers, less ``EDGE_MM`` at the border."""
    rows = np.flatnonzero((toolpath.layer == layer) & toolpath.spray_on
                          & (toolpath.kind == KIND_CODE["infill"]))
    rows = rows[rows > 0]
    a, b = toolpath.position_O[rows - 1, :2], toolpath.position_O[rows, :2]
    n = np.maximum(np.ceil(np.linalg.norm(b - a, axis=1) / (CELL_MM / 2)).astype(int), 1)
    pts = np.concatenate([a[i] + np.linspace(0, 1, n[i] + 1)[:, None] * (b[i] - a[i])
                          for i in range(len(rows))]) if len(rows) else np.zeros((0, 2))
    ny, nx = shape
    x = origin_O[0] + (np.arange(nx) + 0.5) * CELL_MM
    y = origin_O[1] + (np.arange(ny) + 0.5) * CELL_MM
    gx, gy = np.meshgrid(x, y)
    if not len(pts):
        return np.zeros(shape, bool)
    d, _ = cKDTree(pts).query(np.c_[gx.ravel(), gy.ravel()])
    covered = (d <= spacing_mm / 2).reshape(shape)
    return binary_erosion(covered, iterations=int(round(EDGE_MM / CELL_MM)))


def score_top(vertices_O: np.ndarray, toolpath: Toolpath, layer: int, layer_mm: float,
              spacing_mm: float, tolerance_mm: float) -> dict:
    """The top after ``layer`` against the intent: out-of-tolerance area [mm^2] and volume
    beyond the tolerance [mm^3], max |deviation| and the median deviation (the top height
    error) [mm], over the intended footprint's area [mm^2]."""
    v = np.asarray(vertices_O, float)
    lo = v[:, :2].min(axis=0)
    ij = np.floor((v[:, :2] - lo) / CELL_MM).astype(int)
    shape = (ij[:, 1].max() + 1, ij[:, 0].max() + 1)
    top = np.full(shape, -np.inf)
    np.maximum.at(top, (ij[:, 1], ij[:, 0]), v[:, 2])
    foot = intent_footprint(toolpath, layer, spacing_mm, lo, shape) & np.isfinite(top)
    z_intent = (layer + 1) * layer_mm
    d = top[foot] - z_intent
    cell = CELL_MM * CELL_MM
    out = np.abs(d) > tolerance_mm
    return {"layer": layer, "footprint_mm2": float(foot.sum() * cell),
            "out_of_tolerance_mm2": float(out.sum() * cell),
            "out_of_tolerance_mm3": float(np.sum(np.abs(d[out]) - tolerance_mm) * cell),
            "max_abs_deviation_mm": float(np.abs(d).max()) if d.size else 0.0,
            "top_error_mm": float(np.median(d)) if d.size else 0.0}
