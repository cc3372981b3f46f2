"""The reference as the profilers last saw it: its height at each column when last observed.

Three 10 Hz profilers see a column a few times per pass, some of them while the plume is still
depositing there, and the layer ends before the last passes are seen again. The fused surface
of such a column is the surface of its last observation, so comparing it with the reference at
the layer's end calls the deposit that came after an underbuild (on the twin's parts the first
layer read 5-20 % short that way).

:class:`SeenReference` keeps, per reference cell, the reference height when a profile point
last fell within ``radius_mm`` of it, and when. At a layer's end, the growth of the reference
since then (``unseen_mm``, over every column observed at least once) goes to the layer
analysis, which does not call an underbuild of that size (dm2.defects.deviation), and to the
process fit, which measures the deposition scale against what was seen. A column the profilers
no longer see (a ledge far below the top of a tall part, where the plume's tail still lands)
is so compared with the reference of its last observation, not with a reference that went on
growing while the measured surface stood still.

It keeps as well the height of the lowest profile point that marked each cell at its last
observation; with the reference's growth since, that is where the surface is expected now
(:meth:`SeenReference.since_seen`). A surface the fused one holds well below that all around it is
an old top the new one grew over unseen (:mod:`dm2.defects.stale`).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from dm2.defects.stale import SeenSurface
from dm2.reference.height_map import ReferenceMap, cell_of


class SeenReference:
    """Reference height per cell at its last observation.

    Parameters
    ----------
    shape : (ny, nx) of the reference height map
    cell_mm : float [mm], its cell
    radius_mm : float [mm], a profile point observes the cells this close (a voxel's reach)
    """

    def __init__(self, shape, cell_mm: float, radius_mm: float):
        self.cell_mm = float(cell_mm)
        self.heights_mm = np.full(shape, np.nan)
        self.stamp_s = np.full(shape, -np.inf)
        self.surface_mm = np.full(shape, -np.inf)  # lowest point at the last observation
        self._reach = max(int(round(radius_mm / self.cell_mm)), 0)  # cells around a point

    def observe(self, points_O: np.ndarray, stamp_s: float, reference_heights_mm: np.ndarray):
        """Profile points ``points_O (n, 3)`` [mm] seen up to ``stamp_s`` against the
        reference's live height map (same grid)."""
        _observe_cells(np.ascontiguousarray(points_O, np.float64), self.cell_mm, self._reach,
                       float(stamp_s), reference_heights_mm, self.heights_mm, self.stamp_s,
                       self.surface_mm)

    def calibrated(self, reference, rescale: float, plume: float) -> None:
        """The process calibration: ``reference`` (the NearNetReference) scaled what it
        deposited so far by ``rescale``; its plume is widened by ``plume`` here, and the seen
        heights move with it."""
        self.heights_mm *= rescale
        if plume != 1.0:
            before = reference.heights_mm.copy()
            reference.set_plume_factor(plume)
            self.heights_mm += reference.heights_mm - before

    def unseen(self, reference: ReferenceMap) -> ReferenceMap:
        """The reference's growth since each column's last observation (0 where no profile
        point ever fell), as a new map on the reference's grid."""
        return self.since_seen(reference)[0]

    def since_seen(self, reference: ReferenceMap) -> tuple[ReferenceMap, SeenSurface]:
        """:meth:`unseen` and where each cell's surface is expected now (the lowest point's
        height at its last observation plus that growth; ``-inf`` where no profile point ever
        fell), the growth computed once."""
        seen = np.isfinite(self.stamp_s)
        grown = np.maximum(np.nan_to_num(
            np.where(seen, reference.heights_mm - self.heights_mm, 0.0)), 0.0)
        expected = SeenSurface(np.where(seen, self.surface_mm + grown, -np.inf), self.cell_mm)
        return (ReferenceMap(grown, reference.cell_mm, reference.layer, reference.stamp_s),
                expected)


@njit(cache=True, nogil=True)
def _observe_cells(points_O, cell_mm, reach, stamp_s, reference_heights_mm, heights_mm, stamps_s,
                   surface_mm):
    """Cells within ``reach`` cells of each point ``points_O (n, 3)`` [mm] on the plate
    (clipped to its edge) take the reference's height and ``stamp_s``, and the point's height
    as their seen surface (the lowest of the points that mark a cell at one stamp). A point in
    the same cell as the point before it writes nothing new (a profile's points are a few per
    cell) and is skipped."""
    ny, nx = heights_mm.shape
    last_i = last_j = -1
    for k in range(points_O.shape[0]):
        i0, j0 = cell_of(points_O[k, 0], points_O[k, 1], cell_mm, ny, nx)
        if i0 < 0 or (i0 == last_i and j0 == last_j):
            continue
        last_i, last_j = i0, j0
        z = points_O[k, 2]
        for i in range(max(i0 - reach, 0), min(i0 + reach, ny - 1) + 1):
            for j in range(max(j0 - reach, 0), min(j0 + reach, nx - 1) + 1):
                heights_mm[i, j] = reference_heights_mm[i, j]
                if stamps_s[i, j] != stamp_s or z < surface_mm[i, j]:
                    surface_mm[i, j] = z
                stamps_s[i, j] = stamp_s
