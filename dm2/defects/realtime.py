"""Real-time deviation: measured TSDF against the reference in the active region, every frame set.

After every frame set (the three profilers' lines) the TSDF voxels in a box around the
deposition spot are compared with the reference. Along each voxel column the topmost observed
zero crossing of the TSDF (weights ``>= min_weight`` on both sides, + above, - below) gives the
measured surface height, linearly interpolated between voxel centres; its signed distance to
the reference height map (height difference projected on the reference normal) is that
column's deviation. Columns beyond ``delta_global_mm`` are flagged over/underbuilt in a
persistent column map over the plate; an 8-connected patch of flagged columns reaching
``min_region_area_mm2`` raises an alarm at once, without waiting for the layer to end. The
laser lines sample the surface a few mm apart, so unobserved columns between flagged ones are
bridged (morphological closing of radius ``link_mm``) when a patch's area is measured; columns
observed as normal are never counted.

Evidence: as in the layer analysis, the bound decides whether there is a defect and the
tolerance how far it reaches. A patch raises an alarm only when it holds a column beyond its
confidence bound (its TSDF weight, the reference's slope and height,
:mod:`dm2.defects.uncertainty`; ``uncertainty=False`` drops the bound) that is persistent:
flagged for at least ``realtime_persist_s`` of process time and in
``realtime_min_observations`` observations in a row (comparisons with new measurement, not
the same TSDF compared again). A transient at the deposition front or a single noisy frame
set raises nothing.

The comparison follows the measurement (:func:`~dm2.defects.realtime_compare.compare_columns`):
a column is judged again only when its measured crossing changed, never because the
reference grew over a surface measured earlier; and the TSDF's running average lags a surface
under deposition, so a column's measurement is held against the interval from the reference at
its previous observation to the reference now (overbuild above it, underbuild below it). As in
the layer analysis, the bound holds the reference's edge and plume terms
(:mod:`dm2.defects.realtime_curvature`), and columns ``overspray_margin_mm`` or more outside
the planned outline (overspray on the plate) raise no alarm of their own.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from dm2.defects.realtime_compare import (
    NO_WINDOW_TERMS,
    ColumnMaps,
    CompareParams,
    compare_columns,
)
from dm2.defects.realtime_curvature import window_curvatures
from dm2.defects.realtime_kernels import OVER, UNDER, patch_alarms, window_reference_heights

KIND_NAMES = {OVER: "overbuild", UNDER: "underbuild"}


@dataclass(frozen=True)
class RealtimeAlarm:
    """A flagged patch that reached the minimum region area.

    Attributes
    ----------
    stamp_s : float [s], frame set that raised it
    kind : str, ``overbuild`` or ``underbuild``
    area_mm2 : float [mm^2], projected area of the patch then
    centroid_xy_O : (2,) float64 [mm]
    first_flag_s : float [s], when the patch's first column was flagged
    """

    stamp_s: float
    kind: str
    area_mm2: float
    centroid_xy_O: np.ndarray
    first_flag_s: float


@dataclass(frozen=True)
class FrameDeviation:
    """Deviation of one frame set's active region.

    Attributes
    ----------
    stamp_s : float [s]
    xy_O : (k, 2) float64 [mm], centres of the columns with an observed surface
    deviation_mm : (k,) float64 [mm], signed deviation per column (+ above the reference)
    flag : (k,) int8, 0 normal, 1 overbuild, 2 underbuild
    over_area_mm2, under_area_mm2 : float [mm^2], flagged projected area in this window
    alarms : tuple of RealtimeAlarm raised by this frame set
    """

    stamp_s: float
    xy_O: np.ndarray
    deviation_mm: np.ndarray
    flag: np.ndarray
    over_area_mm2: float
    under_area_mm2: float
    alarms: tuple


class RealtimeDeviation:
    """Per-frame-set deviation monitor over the plate's voxel columns.

    Parameters
    ----------
    monitor_cfg : MonitorConfig (``voxel_mm``, ``delta_global_mm``, ``min_weight``,
        ``min_region_area_mm2``, ``truncation_voxels``)
    size_mm : (2,) plate extent [mm]
    radius_mm : float [mm], half width of the box examined around the spot
    z_margin_mm : float [mm], box reaches this far above/below the reference in the window
    link_mm : float [mm], unobserved gaps up to about twice this between flagged columns are
        bridged when patches are measured (laser lines sweep the surface a few mm apart)
    uncertainty : bool, flag against each column's confidence bound too
    outline : dm2.defects.footprint.PlannedOutline or None, the planned footprint: a column
        ``overspray_margin_mm`` or more outside it is overspray on the plate, which raises no
        alarm by itself (it may belong to the patch of a defect nearer the part)
    """

    def __init__(self, monitor_cfg, size_mm=(120.0, 120.0), radius_mm: float = 6.0,
                 z_margin_mm: float = 3.0, link_mm: float = 2.0, uncertainty: bool = True,
                 outline=None):
        self.cfg = monitor_cfg
        self.voxel_mm = float(monitor_cfg.voxel_mm)
        self.radius_mm = float(radius_mm)
        self.z_margin_mm = float(z_margin_mm)
        nx = int(np.ceil(size_mm[0] / self.voxel_mm))
        ny = int(np.ceil(size_mm[1] / self.voxel_mm))
        self.deviation_map_mm = np.full((ny, nx), np.nan)
        self.flag_map = np.zeros((ny, nx), np.int8)
        self.first_flag_s = np.full((ny, nx), np.nan)
        self._alarmed = np.zeros((ny, nx), bool)
        self.flag_count = np.zeros((ny, nx), np.int64)
        self._weight_map = np.zeros((ny, nx))
        self.strong_map = np.zeros((ny, nx), bool)
        self.measured_map_mm = np.full((ny, nx), np.nan)
        self.expected_map_mm = np.full((ny, nx), np.nan)
        u = monitor_cfg.uncertainty
        self._uncertainty = bool(uncertainty)
        self._edge_mm = float(u.edge_mm) if uncertainty else 0.0
        self._plume_rel = float(u.plume_rel) if uncertainty else 0.0
        self._overspray = np.zeros((ny, nx), bool)
        if outline is not None:
            xx, yy = np.meshgrid((np.arange(nx) + 0.5) * self.voxel_mm,
                                 (np.arange(ny) + 0.5) * self.voxel_mm)
            outside = outline.outside_at(np.column_stack([xx.ravel(), yy.ravel()]))
            self._overspray = (outside >= float(monitor_cfg.overspray_margin_mm)).reshape(ny, nx)
        self._bound = ((float(u.confidence_k), float(u.floor_mm), float(u.range_mm),
                        float(u.wall_mm), float(u.height_mm)) if uncertainty else (0.0,) * 5)
        self.persist_s = float(monitor_cfg.realtime_persist_s)
        self.min_observations = int(monitor_cfg.realtime_min_observations)
        r = max(int(round(link_mm / self.voxel_mm)), 1)
        yy, xx = np.mgrid[-r:r + 1, -r:r + 1]
        self._link = xx * xx + yy * yy <= r * r
        self.alarms: list[RealtimeAlarm] = []
        # compare_columns' constant bundles, as plain tuples (dm2.defects.realtime_compare):
        # built once, the maps' arrays are never replaced
        self._maps = tuple(ColumnMaps(self.deviation_map_mm, self.flag_map, self.first_flag_s,
                                      self._alarmed, self.flag_count, self._weight_map,
                                      self.strong_map, self.measured_map_mm,
                                      self.expected_map_mm, self._overspray))
        self._params = tuple(CompareParams(np.float32(monitor_cfg.min_weight), self.voxel_mm,
                                           float(monitor_cfg.delta_global_mm), self._bound,
                                           self._edge_mm))

    def set_model_inflation(self, by_term: dict | None) -> None:
        """Raise the bound's model-error terms (wall, edge, plume) by a layer's factors
        (:mod:`dm2.defects.uncertainty_online`; None or an empty dict: the configured bound).
        Without the uncertainty bound this does nothing."""
        if not self._uncertainty:
            return
        f = by_term or {}
        u = self.cfg.uncertainty
        self._edge_mm = float(u.edge_mm) * float(f.get("edge", 1.0))
        self._plume_rel = float(u.plume_rel) * float(f.get("plume", 1.0))
        k, floor, rng, _, height = self._bound
        self._bound = (k, floor, rng, float(u.wall_mm) * float(f.get("wall", 1.0)), height)
        self._params = tuple(CompareParams(np.float32(self.cfg.min_weight), self.voxel_mm,
                                           float(self.cfg.delta_global_mm), self._bound,
                                           self._edge_mm))

    def flagged_area_mm2(self, kind: int = OVER) -> float:
        """Projected area [mm^2] of all columns currently flagged ``kind`` (1 over, 2 under)."""
        return float(np.count_nonzero(self.flag_map == kind)) * self.voxel_mm ** 2

    def update_from_tsdf(self, tsdf, spot_O, stamp_s: float, reference) -> FrameDeviation:
        """Gather the box around ``spot_O`` (3,) [mm] from a dm2.fusion.tsdf.field.SparseTSDF and
        compare."""
        v = self.voxel_mm
        sx, sy, r = float(spot_O[0]), float(spot_O[1]), self.radius_mm
        ny, nx = self.flag_map.shape
        i0 = min(max(math.floor((sx - r) / v), 0), nx - 1)
        j0 = min(max(math.floor((sy - r) / v), 0), ny - 1)
        i1 = min(max(math.ceil((sx + r) / v), i0 + 1), nx)
        j1 = min(max(math.ceil((sy + r) / v), j0 + 1), ny)
        h = window_reference_heights(np.asarray(reference.heights_mm, np.float64),
                                     float(reference.cell_mm), i0, j0, i1, j1, v)
        z_lo = float(h.min()) - self.z_margin_mm
        z_hi = float(h.max()) + self.z_margin_mm
        k0, k1 = int(np.floor(z_lo / v)), int(np.ceil(z_hi / v))
        d, w = tsdf.dense(np.array([i0, j0, k0]), (i1 - i0, j1 - j0, k1 - k0 + 1))
        return self.update(stamp_s, d, w, (i0, j0, k0), reference, window_heights=h)

    def update(self, stamp_s: float, tsdf_mm: np.ndarray, weight: np.ndarray, origin_voxel,
               reference, window_heights: np.ndarray | None = None) -> FrameDeviation:
        """Compare a dense TSDF box with the reference; update maps; raise alarms.

        Parameters
        ----------
        stamp_s : float [s], stamp of the frame set
        tsdf_mm : (nx, ny, nz) float [mm], signed distance (+ in front of / above the surface)
        weight : (nx, ny, nz) float, fusion weight (0 = unobserved)
        origin_voxel : (3,) int, voxel index of ``tsdf_mm[0, 0, 0]`` (centres at (i + 0.5) * v)
        reference : ReferenceMap or anything with ``heights_mm`` and ``cell_mm`` (e.g. the
            live NearNetReference)
        window_heights : (ny, nx) float64 [mm] or None, the reference at the box's voxel
            columns when the caller has it already
        """
        v = self.voxel_mm
        i0, j0, k0 = (int(x) for x in origin_voxel)
        d = np.asarray(tsdf_mm, np.float32)
        hw = window_heights
        if hw is None:
            hw = window_reference_heights(np.asarray(reference.heights_mm, np.float64),
                                          float(reference.cell_mm), i0, j0, i0 + d.shape[0],
                                          j0 + d.shape[1], v)
        curv = lap = NO_WINDOW_TERMS
        plume_mm2 = self._plume_rel * float(getattr(reference, "plume_sigma_mm", 0.0)) ** 2
        if self._edge_mm > 0.0 or plume_mm2 > 0.0:
            ny, nx = self.flag_map.shape
            curv, lap = window_curvatures(np.asarray(reference.heights_mm, np.float64),
                                          float(reference.cell_mm), i0, j0, i0 + d.shape[0],
                                          j0 + d.shape[1], v, nx, ny)
        window = (hw, curv, lap, plume_mm2)  # a ReferenceWindow's fields, as a plain tuple
        gi, gj, dev, flag, newly = compare_columns(
            d, np.asarray(weight, np.float32), (i0, j0, k0), window, self._maps, self._params,
            float(stamp_s))
        n_over = int(np.count_nonzero(flag == OVER))
        n_under = int(np.count_nonzero(flag == UNDER))
        # a patch can only reach the alarm area, or hold a persistent column, through a column
        # flagged anew or observed flagged again: columns observed as normal only shrink
        # patches and clear their marks
        alarms = self._raise_alarms(stamp_s, gi, gj) if newly else ()
        xy = np.empty((gi.shape[0], 2))
        xy[:, 0] = (gi + 0.5) * v
        xy[:, 1] = (gj + 0.5) * v
        cell_area = v * v
        return FrameDeviation(float(stamp_s), xy, dev, flag, n_over * cell_area,
                              n_under * cell_area, alarms)

    def _raise_alarms(self, stamp_s, gi, gj) -> tuple:
        v = self.voxel_mm
        pad = int(np.ceil(2 * self.radius_mm / v)) + self._link.shape[0]
        ny, nx = self.flag_map.shape
        r0, r1 = max(gj.min() - pad, 0), min(gj.max() + pad + 1, ny)
        c0, c1 = max(gi.min() - pad, 0), min(gi.max() + pad + 1, nx)
        flags = self.flag_map[r0:r1, c0:c1]
        alarmed = self._alarmed[r0:r1, c0:c1]
        out = []
        min_cells = max(self.cfg.min_region_area_mm2 / (v * v), 1.0)
        deviation_mm = self.deviation_map_mm[r0:r1, c0:c1]
        first_flag_s = self.first_flag_s[r0:r1, c0:c1]
        mature = (self.strong_map[r0:r1, c0:c1]
                  & (self.flag_count[r0:r1, c0:c1] >= self.min_observations)
                  & (stamp_s - first_flag_s >= self.persist_s))
        for kind in (OVER, UNDER):  # over first: its marks count for the under patches
            sizes, stats = patch_alarms(flags, kind, deviation_mm, alarmed, first_flag_s,
                                        self._link, min_cells, mature)
            for size, (row, col, first) in zip(sizes.tolist(), stats.tolist(), strict=True):
                centroid = np.array([(col + c0 + 0.5) * v, (row + r0 + 0.5) * v])
                out.append(RealtimeAlarm(float(stamp_s), KIND_NAMES[kind], size * v * v,
                                         centroid, first))
        self.alarms.extend(out)
        return tuple(out)
