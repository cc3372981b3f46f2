"""The calibration layer's top, kept so that each later layer's growth is read where it is
measured.

The process fit (:mod:`dm2.process.process_fit`) follows the deposition scale by the growth of
the part's top since the calibration layer against the growth of the reference. Each layer's
top (its plateau's well observed vertices) is another set of points: a narrow part's first-layer
plateau is a 7 mm ring, the third layer's its few highest patches. Medians over different sets
compare different places: the first layer's whole plateau, lowered at its edges by the plume,
against a later layer's highest patch read a 30 mm wide plate with a 10 mm hole 3 % too
efficient (1.212 against the twin's 1.173).

:class:`CalibrationTop` keeps the calibration layer's top vertices (where they were, what was
measured there, the reference as the profilers had seen it) and its reference map. Once the
calibration's scale and plume width are known, the reference of that layer is brought to them
as the near-net reference itself is (scaled, then widened by
:func:`dm2.reference.plume_width.rescale_plume`). A later layer's vertex then has, at its own
place, both the calibration layer's reference and, carried from the nearest calibration vertex
within ``MATCH_MM``, how far the measurement stood from it. :meth:`growth_ratio` is the
area-weighted median growth of the measurement over that of the reference, read as the
reference's growth plus the median difference of the two, the way the calibration reads a
height (:func:`dm2.process.process_top.top_heights`).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from dm2.reference.height_map import ReferenceMap, bilinear_height
from dm2.reference.plume_width import rescale_plume

MATCH_MM = 0.5  # a later vertex takes the calibration residual of a vertex this close, at most


class CalibrationTop:
    """The calibration layer's top: vertices ``xy_O (n, 2)`` [mm], measured heights ``z_mm
    (n,)``, the reference there as seen ``seen_mm (n,)`` (the layer's map less what the
    profilers had not seen yet), and the layer's reference map ``close_map`` deposited at
    ``scale``."""

    def __init__(self, close_map: ReferenceMap, scale: float, xy_O: np.ndarray,
                 z_mm: np.ndarray, seen_mm: np.ndarray):
        self.close_map = close_map
        self.scale = float(scale)
        self.xy_O = np.asarray(xy_O, np.float64).reshape(-1, 2)
        self.z_mm = np.asarray(z_mm, np.float64)
        # what the profilers had not seen of the reference, at the layer's own scale
        self.unseen_mm = close_map.height_at(self.xy_O) - np.asarray(seen_mm, np.float64)
        self._tree = cKDTree(self.xy_O)
        self._heights_mm: np.ndarray | None = None  # the layer's reference, calibrated
        self._residual_mm: np.ndarray | None = None  # measured less seen reference, calibrated
        self._unseen_now_mm = self.unseen_mm  # the unseen reference, calibrated

    def calibrate(self, scale: float, plume: float) -> None:
        """The calibration's ``scale`` and ``plume`` factor: the layer's reference brought to
        them (deposited so far scaled by ``scale / self.scale``, widened ``plume`` times)."""
        rescale = float(scale) / self.scale
        h = np.array(self.close_map.heights_mm, np.float64) * rescale
        if plume != 1.0 and self.close_map.plume_sigma_mm > 0:
            rescale_plume(h, self.close_map.cell_mm, self.close_map.plume_sigma_mm, plume)
        self._heights_mm = h
        seen = self._at(self.xy_O) - self.unseen_mm * rescale
        self._residual_mm = self.z_mm - seen
        self._unseen_now_mm = self.unseen_mm * rescale

    def _at(self, xy_O: np.ndarray) -> np.ndarray:
        return bilinear_height(self._heights_mm, self.close_map.cell_mm, xy_O)

    def growth_ratio(self, xy_O: np.ndarray, z_mm: np.ndarray, seen_mm: np.ndarray,
                     area_mm2: np.ndarray, enough: int) -> tuple[float | None, float, int]:
        """``(ratio, reference growth [mm], vertices)``: a later layer's top vertices at
        ``xy_O (m, 2)`` with measured ``z_mm`` and seen reference ``seen_mm`` against the
        calibration layer at the same places. ``ratio`` is the measured over the reference
        growth since the calibration, or None when fewer than ``enough`` vertices have a
        calibration vertex within ``MATCH_MM`` (or before :meth:`calibrate`)."""
        if self._heights_mm is None or not len(xy_O):
            return None, 0.0, 0
        dist, idx = self._tree.query(np.asarray(xy_O, np.float64).reshape(-1, 2),
                                     distance_upper_bound=MATCH_MM)
        ok = np.isfinite(dist)
        if ok.sum() < enough:
            return None, 0.0, int(ok.sum())
        idx = idx[ok]
        # the calibration layer's reference here, as the profilers had seen it
        cal_seen = self._at(np.asarray(xy_O)[ok]) - self._unseen_now_mm[idx]
        ref_growth = np.asarray(seen_mm)[ok] - cal_seen
        meas_growth = np.asarray(z_mm)[ok] - (cal_seen + self._residual_mm[idx])
        w = np.asarray(area_mm2)[ok]
        ref_mm = weighted_median(ref_growth, w)
        if ref_mm <= 0.0:
            return None, ref_mm, int(ok.sum())
        meas_mm = ref_mm + weighted_median(meas_growth - ref_growth, w)
        return meas_mm / ref_mm, ref_mm, int(ok.sum())


def weighted_median(values: np.ndarray, weights: np.ndarray) -> float:
    """The value below which half the total weight lies."""
    order = np.argsort(values, kind="stable")
    cw = np.cumsum(weights[order])
    return float(values[order][min(int(np.searchsorted(cw, 0.5 * cw[-1])), cw.size - 1)])
