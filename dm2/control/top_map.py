"""The measured top of the part as a height map in ``O``, from a layer's fused surface.

Each grid cell keeps the highest vertex that faces up (normal ``z_O`` above ``MIN_UP``) and
was fused with at least ``min_weight``; cells with none are unmeasured (NaN). The correction
reads the top averaged over the plume's width around a segment (a Gaussian normalised over
the measured cells only), since one segment's deposit spreads that wide.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import gaussian_filter

MIN_UP = 0.5  # a vertex whose normal's z_O is below this is a flank, not the top


@dataclass(frozen=True)
class TopMap:
    """Cell-centred height map: cell ``(j, i)`` has its centre at
    ``origin_O + (i + 0.5, j + 0.5) * cell_mm``.

    z_mm : (ny, nx) float64 [mm], NaN where unmeasured
    origin_O : (2,) float64 [mm], the grid's lower-left corner in ``O``
    cell_mm : float [mm]
    """

    z_mm: np.ndarray
    origin_O: np.ndarray
    cell_mm: float

    def _index(self, xy_O: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        ij = np.floor((np.asarray(xy_O, float)[:, :2] - self.origin_O) / self.cell_mm).astype(int)
        ny, nx = self.z_mm.shape
        inside = (ij[:, 0] >= 0) & (ij[:, 0] < nx) & (ij[:, 1] >= 0) & (ij[:, 1] < ny)
        return np.clip(ij[:, 1], 0, ny - 1), np.clip(ij[:, 0], 0, nx - 1), inside

    def sample(self, xy_O: np.ndarray, sigma_mm: float = 0.0) -> np.ndarray:
        """The top at ``xy_O`` (n, 2+) [mm], averaged with a Gaussian of ``sigma_mm`` over the
        measured cells; NaN outside the grid or where nothing near was measured."""
        z = self.z_mm
        if sigma_mm > 0:
            seen = np.isfinite(z)
            s = sigma_mm / self.cell_mm
            num = gaussian_filter(np.where(seen, z, 0.0), s, mode="constant")
            den = gaussian_filter(seen.astype(float), s, mode="constant")
            with np.errstate(invalid="ignore", divide="ignore"):
                z = np.where(den > 0.2, num / np.maximum(den, 1e-12), np.nan)
        j, i, inside = self._index(xy_O)
        return np.where(inside, z[j, i], np.nan)


def measured_top(vertices_O: np.ndarray, normals_O: np.ndarray | None, weight: np.ndarray | None,
                 cell_mm: float, min_weight: float = 0.0,
                 bounds_O: tuple[float, float, float, float] | None = None) -> TopMap:
    """The highest up-facing, confidently fused vertex per cell.

    vertices_O : (n, 3) [mm]; normals_O : (n, 3) unit or None (every vertex counts as top);
    weight : (n,) fusion weight or None; bounds_O : (x0, y0, x1, y1) [mm] of the grid, default
    the vertices' extent.
    """
    v = np.asarray(vertices_O, float).reshape(-1, 3)
    keep = np.ones(len(v), bool)
    if normals_O is not None:
        keep &= np.asarray(normals_O, float).reshape(-1, 3)[:, 2] >= MIN_UP
    if weight is not None:
        keep &= np.asarray(weight, float) >= min_weight
    if bounds_O is None:
        lo = v[:, :2].min(axis=0) if len(v) else np.zeros(2)
        hi = v[:, :2].max(axis=0) if len(v) else np.zeros(2)
    else:
        lo, hi = np.array(bounds_O[:2], float), np.array(bounds_O[2:], float)
    n = np.maximum(np.ceil((hi - lo) / cell_mm).astype(int), 1)
    z = np.full((n[1], n[0]), -np.inf)
    top = TopMap(z, lo, float(cell_mm))
    j, i, inside = top._index(v[keep])
    np.maximum.at(z, (j[inside], i[inside]), v[keep][inside, 2])
    z[~np.isfinite(z)] = np.nan
    return top
