"""The calibration layer's top as the profilers see it again once the next layer has begun.

The first-layer calibration (:mod:`dm2.process.process_fit`) measures the deposition scale as
the ratio of the measured to the reference top. The fused surface of a layer at its close lags
the part's true top: the plume's flank keeps depositing on a column after its last observations,
and the fused average still holds the observations made while the column grew. On a thin first
layer that lag is a few per cent of its height (twin parts, 0.8 mm layers: 0.03-0.06 mm, the
calibration 3-5 % low), and an early calibration error stays in the reference of every layer.

In the first seconds of the next layer the profilers sweep the finished top again, most of it
ahead of the spray. A profile point that falls on a column the reference has not grown since the
close (``FRESH_GROWTH`` of its height) sees the calibration layer's final surface, with no
averaging behind it. :class:`ReobservedTop` keeps, per reference cell of the calibration
layer's plateau (reference slope at most ``PLATEAU_SLOPE``, at least ``PLATEAU_FRACTION`` of the
top's 95th-percentile height), the mean height of such points seen in a window of stream time
after the close. Its :meth:`estimate` is the reference's median plateau height plus the median
measured-minus-reference difference over the cells seen, against the reference's median height:
the scale the calibration then uses, when at least ``MIN_CELLS`` cells were seen (else the
calibration keeps the fused layer's estimate). Like the fused layer's estimate, it is read only
on the cells where the plume width does not move the reference, when at least ``MIN_CELLS``
of those were seen (:func:`dm2.process.process_top.plume_insensitive`). Cells near a flagged
defect of the calibration layer are left out, as the fused layer's estimate leaves out defect
vertices. So are cells seen again far from where the fused layer had them (``CHANGED_MM``, or
four robust spreads, off the cells' median difference): the lag only adds a few hundredths of
a millimetre, so a cell that moved more changed after the close (a dent or a bump as the next
layer starts, which the fused layer could not flag). A fault at the start of the next
layer's path can be a large share of the few hundred cells seen again: a 4 mm dent took the
triangle's calibration to 0.916-0.924, against 0.952-0.958 without it. Only its core is
left out so (at 0.15 mm); its gentle flank, within the cells' spread, still lowers a small
plateau (0.922 at the same seed).
"""

from __future__ import annotations

import numpy as np
from numba import njit
from scipy.spatial import cKDTree

from dm2.process.process_top import (
    MIN_HEIGHT_MM,
    PLATEAU_FRACTION,
    PLATEAU_SLOPE,
    plume_insensitive,
)
from dm2.reference.height_map import ReferenceMap, cell_of

FRESH_GROWTH = 0.01  # a column counts as finished while the reference grew less than this share
MIN_CELLS = 200  # reference cells seen again on the plateau for an estimate (12.5 mm2 at 0.25)
DEFECT_CLEARANCE_MM = 1.0  # cells this close to a flagged defect vertex are left out
CHANGED_MM = 0.15  # a cell seen again this much (at least) off the fused layer changed since
FUSED_MATCH_MM = 0.5  # a cell's fused height: the calibration top's vertex this close, at most


class ReobservedTop:
    """Profile points on the calibration layer's finished plateau, in a window after its close.

    Parameters
    ----------
    close_map : the calibration layer's reference at its close
    since_s, until_s : float [s], the window of profile stamps (the close, the fit's time)
    """

    def __init__(self, close_map: ReferenceMap, since_s: float, until_s: float):
        self.close_map = close_map
        self.cell_mm = float(close_map.cell_mm)
        self.close_mm = np.asarray(close_map.heights_mm, np.float64)
        self.since_s, self.until_s = float(since_s), float(until_s)
        gy, gx = np.gradient(self.close_mm, self.cell_mm)
        top = self.close_mm >= MIN_HEIGHT_MM
        p95 = np.percentile(self.close_mm[top], 95) if top.any() else np.inf
        self.plateau = (top & (np.hypot(gx, gy) <= PLATEAU_SLOPE)
                        & (self.close_mm >= PLATEAU_FRACTION * p95))
        self._sum_mm = np.zeros_like(self.close_mm)
        self._count = np.zeros(self.close_mm.shape, np.int64)

    def observe(self, points_O: np.ndarray, stamp_s: float, heights_mm: np.ndarray) -> None:
        """Points ``(n, 3)`` [mm] of a profile stamped ``stamp_s``, with the reference's live
        heights (same grid) integrated up to that stamp."""
        if self.since_s < stamp_s <= self.until_s:
            _accumulate(np.ascontiguousarray(points_O, np.float64), self.cell_mm, self.plateau,
                        self.close_mm, heights_mm, self._sum_mm, self._count)

    def estimate(self, defect_xy_O: np.ndarray | None = None,
                 fused: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[float | None, int]:
        """``(measured / reference height ratio or None, cells used)``; cells within
        ``DEFECT_CLEARANCE_MM`` of ``defect_xy_O (k, 2)`` [mm] are left out, and with ``fused``
        (the calibration layer's top vertices ``xy_O (n, 2)`` and fused heights ``z_mm (n,)``
        [mm]) the cells that changed since the close (:func:`changed_since_close`)."""
        i, j = np.nonzero(self._count)
        xy = np.c_[(j + 0.5) * self.cell_mm, (i + 0.5) * self.cell_mm]
        if defect_xy_O is not None and len(defect_xy_O):
            far = cKDTree(np.asarray(defect_xy_O)[:, :2]).query(
                xy, distance_upper_bound=DEFECT_CLEARANCE_MM)[0] > DEFECT_CLEARANCE_MM
            i, j, xy = i[far], j[far], xy[far]
        if fused is not None and i.size:
            same = ~changed_since_close(xy, self._sum_mm[i, j] / self._count[i, j], *fused)
            i, j, xy = i[same], j[same], xy[same]
        if i.size < MIN_CELLS:
            return None, int(i.size)
        flat = plume_insensitive(self.close_map, xy, MIN_CELLS)  # where the width does not matter
        if flat is not None:
            i, j = i[flat], j[flat]
        ref = self.close_mm[i, j]
        measured = self._sum_mm[i, j] / self._count[i, j]
        ref_mm = float(np.median(ref))
        return (ref_mm + float(np.median(measured - ref))) / ref_mm, int(i.size)


def changed_since_close(xy_O: np.ndarray, seen_mm: np.ndarray, fused_xy_O: np.ndarray,
                        fused_z_mm: np.ndarray) -> np.ndarray:
    """Cells (centres ``xy_O (m, 2)`` [mm], heights seen again ``seen_mm (m,)``) that changed
    since the close: their difference to the nearest fused top vertex within
    ``FUSED_MATCH_MM`` lies more than ``CHANGED_MM``, and more than four robust spreads, off
    the median difference of all such cells. Cells with no fused vertex that close are kept."""
    changed = np.zeros(len(xy_O), bool)
    if not len(fused_xy_O) or not len(xy_O):
        return changed
    dist, k = cKDTree(np.asarray(fused_xy_O)[:, :2]).query(
        xy_O, distance_upper_bound=FUSED_MATCH_MM)
    near = np.isfinite(dist)
    if not near.any():
        return changed
    d = np.asarray(seen_mm)[near] - np.asarray(fused_z_mm)[k[near]]
    med = float(np.median(d))
    spread = 1.4826 * float(np.median(np.abs(d - med)))
    changed[near] = np.abs(d - med) > max(CHANGED_MM, 4.0 * spread)
    return changed


@njit(cache=True, nogil=True)
def _accumulate(points_O, cell_mm, plateau, close_mm, heights_mm, sum_mm, count):
    """Add each point's height to its cell where that cell is on the plateau and its reference
    grew less than ``FRESH_GROWTH`` of its height since the close."""
    ny, nx = close_mm.shape
    for k in range(points_O.shape[0]):
        i, j = cell_of(points_O[k, 0], points_O[k, 1], cell_mm, ny, nx)
        if i < 0 or not plateau[i, j]:
            continue
        if heights_mm[i, j] - close_mm[i, j] <= FRESH_GROWTH * close_mm[i, j]:
            sum_mm[i, j] += points_O[k, 2]
            count[i, j] += 1
