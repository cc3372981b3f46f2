"""Stale tops: a measured surface below where the surface is expected all around it.

The fused surface of a column is what its voxels last held. Where the profilers' rays stop
reaching a column (the centre of a narrow top seen only at grazing angles between two raised
rims), the column keeps the top of its last direct observation, and the new top grows above it
unseen. Profile points that fall on the neighbouring columns still mark it as seen
(:class:`dm2.pipeline.seen_reference.SeenReference` marks the cells within a voxel's reach of a
point), so the reference's growth since then is not counted as unseen there; the old top then
reads as an underbuild as deep as the growth it missed (paper experiment 1: 4.3 mm at the
centre of the reduced tower, in columns whose neighbours were seen at the true height).

:class:`SeenSurface` holds, per reference cell, where the surface is expected now: the height
of the lowest profile point that marked the cell at its last observation, plus the reference's
growth since. A vertex that lies more than ``STALE_MARGIN_MM`` below the lowest of those within
``STALE_REACH_MM`` of it, once its own column's unseen growth is added, is not a surface the
profilers saw: :func:`stale_gap_mm` is that gap, and the deviation adds it to an underbuild
as it adds the unseen growth (:func:`dm2.defects.deviation.layer_deviation`), so the vertex
reads as the lowest surface expected around it. The old top and the steep mesh that joins it to
the seen top around it are both such vertices. A vertex that faces up (a top, ``n_z >=
TOP_MIN_NZ``) is also held to its own cell alone: inside an old top, cells last seen long ago
(whose points stood on the old top, and whose reference grew less since than the part did)
would otherwise hold the whole patch down. What was seen stays the evidence:

* a dent or a clog whose own points mark its cells reads at its own depth;
* a wall has the cells beyond it (the plate, a hole's floor, a lower flank: seen low, the
  reference grown little there since) or cells never seen within the reach: its vertices (not
  up-facing) are never lifted, and neither is a top at an edge (its own cell saw that top);
* a column no profile point ever marked is not lifted (its growth is not unseen either).

The margin covers what a seen point may stand above a sound surface within the reach: 0.5 mm
sideways at up to 45 deg of slope, plus the voxel's quantisation.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import minimum_filter

STALE_MARGIN_MM = 1.0  # a surface this far below the lowest point seen around it is stale
STALE_REACH_MM = 0.5  # "around": the cells within this distance (a square window)
TOP_MIN_NZ = float(np.cos(np.radians(45.0)))  # a vertex faces up (a top) from this n_z on


@dataclass(frozen=True)
class SeenSurface:
    """Where each reference cell's surface is expected now [mm]: the lowest profile point at
    its last observation plus the reference's growth since.

    Attributes
    ----------
    heights_mm : (ny, nx) float64 [mm], ``-inf`` where no profile point ever fell
    cell_mm : float [mm], the reference grid's cell (cell ``(j, i)`` covers
        ``[i, i + 1) * cell_mm`` in x and ``[j, j + 1) * cell_mm`` in y)
    """

    heights_mm: np.ndarray
    cell_mm: float

    def lowest_near(self, xy_O: np.ndarray, reach_mm: float = STALE_REACH_MM) -> np.ndarray:
        """Lowest seen height [mm] (n,) over the cells within ``reach_mm`` (a square window)
        of the cell holding each ``xy_O (n, 2)``; ``-inf`` off the grid or where any of them
        was never seen."""
        xy = np.asarray(xy_O, np.float64).reshape(-1, 2)
        r = max(int(np.ceil(reach_mm / self.cell_mm - 1e-9)), 0)
        low = self.heights_mm if r == 0 else minimum_filter(self.heights_mm, size=2 * r + 1,
                                                             mode="constant", cval=-np.inf)
        ny, nx = low.shape
        with np.errstate(invalid="ignore"):
            i = np.floor(xy[:, 0] / self.cell_mm)
            j = np.floor(xy[:, 1] / self.cell_mm)
        ok = (i >= 0) & (j >= 0) & (i < nx) & (j < ny)
        out = np.full(len(xy), -np.inf)
        out[ok] = low[j[ok].astype(np.int64), i[ok].astype(np.int64)]
        return out


def stale_gap_mm(vertices_O: np.ndarray, seen: SeenSurface | None,
                 unseen_mm: np.ndarray | None = None,
                 normals_O: np.ndarray | None = None) -> np.ndarray | None:
    """How far [mm] (n,) each vertex, raised by its column's unseen growth ``unseen_mm`` (n,)
    (or None), lies below the lowest surface expected around it
    (:meth:`SeenSurface.lowest_near`), where that is more than :data:`STALE_MARGIN_MM`; an
    up-facing vertex (``normals_O`` given, ``n_z >= TOP_MIN_NZ``) is also compared with its own
    cell alone. 0 elsewhere. None without a seen surface."""
    if seen is None:
        return None
    v = np.asarray(vertices_O, np.float64)
    z = v[:, 2] if unseen_mm is None else v[:, 2] + np.asarray(unseen_mm, np.float64)
    gap = seen.lowest_near(v[:, :2]) - z
    if normals_O is not None:
        up = np.asarray(normals_O, np.float64)[:, 2] >= TOP_MIN_NZ
        own = seen.lowest_near(v[:, :2], reach_mm=0.0) - z
        gap = np.where(up & (own > gap), own, gap)
    return np.where(gap > STALE_MARGIN_MM, gap, 0.0)
