"""Splitting the stream into layers: from layer marks, else from the toolpath, else one layer.

With layer marks (the controller reports each layer's start), marks decide. Without them, the
layer at a profile's time is the layer of the toolpath point nearest to the deposition spot, as
the paper does; the toolpath polyline is resampled every ``spacing_mm`` so long raster moves are
matched along their length, and layers only ever advance. Without either, the whole run is layer 0.
"""

from __future__ import annotations

import logging

import numpy as np
from scipy.spatial import cKDTree

from dm2.core.messages import Toolpath

log = logging.getLogger(__name__)


def resample_toolpath(toolpath: Toolpath, spacing_mm: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """Points ``(k, 3)`` [mm] along the toolpath polyline every ``spacing_mm`` at most, and the
    layer ``(k,)`` of the move each point lies on (a move takes the layer of its end vertex)."""
    p = toolpath.position_O
    if len(p) == 0:
        return np.zeros((0, 3)), np.zeros(0, np.int32)
    seg = np.diff(p, axis=0)
    steps = np.maximum(np.ceil(np.linalg.norm(seg, axis=1) / spacing_mm).astype(np.int64), 1)
    seg_idx = np.repeat(np.arange(len(seg)), steps)
    frac = (np.arange(steps.sum()) - np.repeat(np.cumsum(steps) - steps, steps)) / \
        np.repeat(steps, steps)
    pts = p[seg_idx] + seg[seg_idx] * frac[:, None]
    layers = np.where(frac == 0, toolpath.layer[seg_idx], toolpath.layer[seg_idx + 1])
    return np.vstack([pts, p[-1:]]), np.concatenate([layers, toolpath.layer[-1:]]).astype(np.int32)


class LayerTracker:
    """The current layer of the stream.

    Parameters
    ----------
    toolpath : optional, used when the stream carries no layer marks
    max_distance_mm : float [mm], a spot farther than this from the toolpath (approach moves,
        home) does not change the layer
    """

    def __init__(self, toolpath: Toolpath | None = None, max_distance_mm: float = 5.0):
        self.layer = 0
        self.max_distance_mm = float(max_distance_mm)
        self.source = "single"
        self._tree = None
        self._tree_layer = None
        if toolpath is not None and len(toolpath):
            pts, lay = resample_toolpath(toolpath)
            self._tree = cKDTree(pts)
            self._tree_layer = lay
            self.layer = int(toolpath.layer[0])
            self.source = "toolpath"

    def on_mark(self, layer: int) -> int | None:
        """Apply a layer mark; returns the layer that just finished, if one did."""
        if self.source != "marks":
            log.info("layers: following the controller's layer marks")
            self.source = "marks"
            self._tree = None
        if layer > self.layer:
            finished, self.layer = self.layer, layer
            return finished
        return None

    def on_spots(self, spots_O: np.ndarray) -> list[int]:
        """Advance along the toolpath with deposition spots ``(k, 3)`` [mm] in stream order;
        returns the layers that finished (in order)."""
        if self._tree is None or len(spots_O) == 0:
            return []
        dist, idx = self._tree.query(np.asarray(spots_O).reshape(-1, 3))
        finished = []
        for d, i in zip(dist, idx, strict=True):
            cand = int(self._tree_layer[i])
            if d <= self.max_distance_mm and cand > self.layer:
                finished.append(self.layer)
                self.layer = cand
        return finished
