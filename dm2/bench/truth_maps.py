"""The twin's per-layer truth maps: the deviation its faults caused, as a height field in O.

A twin run writes ``truth/deviation_LLL.npz`` for every layer ``LLL`` (see
``twin.world.truth.write_deviation_maps``)::

    deviation_mm : (ny, nx) float32 [mm], faulty minus fault-free true surface (same seed and
                   [twin_process]); positive = material the faults added
    surface_mm   : (ny, nx) float32 [mm], the faulty true surface heights
    cell_mm      : float [mm], grid spacing
    x0_mm, y0_mm : float [mm], O coordinates of cell (0, 0)'s centre
    layer        : int

This module reads them (no twin import) and answers the scoring's geometric questions: which
cells carry a deviation of a sign beyond a level, dilated by a radius, and what share of a set
of weighted points lies there.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy import ndimage


@dataclass
class TruthMap:
    """One layer's true fault-caused deviation (see the module docstring).

    Attributes
    ----------
    layer : int
    deviation_mm : (ny, nx) float [mm]
    cell_mm, x0_mm, y0_mm : float [mm], grid spacing and first cell centre in O
    """

    layer: int
    deviation_mm: np.ndarray
    cell_mm: float
    x0_mm: float = 0.0
    y0_mm: float = 0.0
    _masks: dict = field(default_factory=dict, repr=False)

    def mask(self, sign: int, level_mm: float, dilate_mm: float = 0.0) -> np.ndarray:
        """Cells where ``sign * deviation >= level_mm``, grown by ``dilate_mm`` (Euclidean)."""
        key = (int(sign), float(level_mm), float(dilate_mm))
        m = self._masks.get(key)
        if m is None:
            m = sign * self.deviation_mm >= level_mm
            if dilate_mm > 0 and m.any():
                m = ndimage.distance_transform_edt(~m, sampling=self.cell_mm) <= dilate_mm
            self._masks[key] = m
        return m

    def cells_of(self, xy_O) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(rows, cols, inside) of the cells holding points ``xy_O (k, 2)`` [mm]."""
        xy = np.asarray(xy_O, dtype=np.float64).reshape(-1, 2)
        ny, nx = self.deviation_mm.shape
        cols = np.floor((xy[:, 0] - self.x0_mm) / self.cell_mm + 0.5).astype(np.int64)
        rows = np.floor((xy[:, 1] - self.y0_mm) / self.cell_mm + 0.5).astype(np.int64)
        inside = (cols >= 0) & (cols < nx) & (rows >= 0) & (rows < ny)
        return np.clip(rows, 0, ny - 1), np.clip(cols, 0, nx - 1), inside

    def fraction_in(self, mask: np.ndarray, xy_O, weights=None) -> float:
        """Weighted share of the points ``xy_O`` lying in ``mask`` (0 outside the map)."""
        rows, cols, inside = self.cells_of(xy_O)
        w = np.ones(rows.size) if weights is None else np.asarray(weights, np.float64)
        total = float(w.sum())
        if total <= 0:
            return 0.0
        return float(w[inside & mask[rows, cols]].sum() / total)

    def area_mm2(self, mask: np.ndarray) -> float:
        return float(np.count_nonzero(mask)) * self.cell_mm ** 2


def load_truth_maps(truth_dir) -> dict[int, TruthMap]:
    """Every ``deviation_LLL.npz`` in ``truth_dir``, by layer (empty when there are none)."""
    out: dict[int, TruthMap] = {}
    folder = Path(truth_dir)
    if not folder.is_dir():
        return out
    for path in sorted(folder.glob("deviation_*.npz")):
        if not re.fullmatch(r"deviation_\d{3,}\.npz", path.name):
            continue
        with np.load(path) as z:
            try:
                out[int(z["layer"])] = TruthMap(
                    int(z["layer"]), np.asarray(z["deviation_mm"], np.float64),
                    float(z["cell_mm"]), float(z["x0_mm"]), float(z["y0_mm"]))
            except KeyError as exc:
                raise ValueError(f"{path}: truth map lacks the field {exc}") from None
    return out
