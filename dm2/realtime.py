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
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit
from scipy import ndimage

from dm2.refmap import bilinear_height

OVER, UNDER = 1, 2
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


@njit(cache=True)
def _column_crossings(d, w, min_weight):
    """Fractional voxel index (nx, ny) of the topmost - to + crossing along z, NaN if none."""
    nx, ny, nz = d.shape
    out = np.full((nx, ny), np.nan)
    for i in range(nx):
        for j in range(ny):
            for k in range(nz - 2, -1, -1):
                if w[i, j, k] < min_weight or w[i, j, k + 1] < min_weight:
                    continue
                a, b = d[i, j, k], d[i, j, k + 1]
                if a < 0.0 <= b:
                    out[i, j] = k + (-a) / (b - a)
                    break
    return out


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
    """

    def __init__(self, monitor_cfg, size_mm=(120.0, 120.0), radius_mm: float = 6.0,
                 z_margin_mm: float = 3.0, link_mm: float = 2.0):
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
        r = max(int(round(link_mm / self.voxel_mm)), 1)
        yy, xx = np.mgrid[-r:r + 1, -r:r + 1]
        self._link = xx * xx + yy * yy <= r * r
        self.alarms: list[RealtimeAlarm] = []

    def flagged_area_mm2(self, kind: int = OVER) -> float:
        """Projected area [mm^2] of all columns currently flagged ``kind`` (1 over, 2 under)."""
        return float(np.count_nonzero(self.flag_map == kind)) * self.voxel_mm ** 2

    def update_from_tsdf(self, tsdf, spot_O, stamp_s: float, reference) -> FrameDeviation:
        """Gather the box around ``spot_O`` (3,) [mm] from a dm2.tsdf.SparseTSDF and compare."""
        v = self.voxel_mm
        lo_xy = np.asarray(spot_O[:2], float) - self.radius_mm
        hi_xy = np.asarray(spot_O[:2], float) + self.radius_mm
        ny, nx = self.flag_map.shape
        i0, j0 = np.clip(np.floor(lo_xy / v).astype(int), 0, [nx - 1, ny - 1])
        i1, j1 = np.clip(np.ceil(hi_xy / v).astype(int), [i0 + 1, j0 + 1], [nx, ny])
        h = _window_heights(reference, (i0, j0, i1, j1), v)
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
        cross = _column_crossings(np.asarray(tsdf_mm, np.float32), np.asarray(weight, np.float32),
                                  np.float32(self.cfg.min_weight))
        ii, jj = np.nonzero(np.isfinite(cross))
        gi, gj = ii + i0, jj + j0
        ny, nx = self.flag_map.shape
        inside = (gi >= 0) & (gi < nx) & (gj >= 0) & (gj < ny)
        ii, jj, gi, gj = ii[inside], jj[inside], gi[inside], gj[inside]
        z = (k0 + cross[ii, jj] + 0.5) * v
        xy = np.column_stack([(gi + 0.5) * v, (gj + 0.5) * v])
        box = (i0, j0, i0 + cross.shape[0], j0 + cross.shape[1])
        hw = _window_heights(reference, box, v) if window_heights is None else window_heights
        dev = _reference_distance(hw, v, ii, jj, z)
        dg = float(self.cfg.delta_global_mm)
        flag = np.where(dev > dg, OVER, np.where(dev < -dg, UNDER, 0)).astype(np.int8)
        self.deviation_map_mm[gj, gi] = dev
        newly = (flag != 0) & (self.flag_map[gj, gi] != flag)
        self.first_flag_s[gj[newly], gi[newly]] = stamp_s
        self.flag_map[gj, gi] = flag
        self._alarmed[gj[flag == 0], gi[flag == 0]] = False
        alarms = self._raise_alarms(stamp_s, gi, gj) if np.any(flag) else ()
        cell_area = v * v
        return FrameDeviation(float(stamp_s), xy, dev, flag,
                              float(np.count_nonzero(flag == OVER)) * cell_area,
                              float(np.count_nonzero(flag == UNDER)) * cell_area, alarms)

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
        unseen = np.isnan(self.deviation_map_mm[r0:r1, c0:c1])
        for kind in (OVER, UNDER):
            hit = flags == kind
            if not hit.any():
                continue
            # bridge the unobserved gaps between the swept laser lines (never observed-normal)
            patch = (ndimage.binary_closing(hit, self._link) & (hit | unseen)) | hit
            labels, n = ndimage.label(patch, structure=np.ones((3, 3), bool))
            if n == 0:
                continue
            sizes = np.bincount(labels.ravel(), minlength=n + 1)
            already = np.bincount(labels[alarmed].ravel(), minlength=n + 1)
            for lab in np.flatnonzero((sizes >= min_cells) & (already == 0)):
                if lab == 0:
                    continue
                rows, cols = np.nonzero(labels == lab)
                centroid = np.array([(cols.mean() + c0 + 0.5) * v, (rows.mean() + r0 + 0.5) * v])
                first = float(np.nanmin(self.first_flag_s[rows + r0, cols + c0]))
                out.append(RealtimeAlarm(float(stamp_s), KIND_NAMES[kind],
                                         float(sizes[lab]) * v * v, centroid, first))
                alarmed[rows, cols] = True
        self.alarms.extend(out)
        return tuple(out)


def _window_heights(reference, box, v) -> np.ndarray:
    """Reference heights [mm] (ny, nx) at the voxel columns of ``box = (i0, j0, i1, j1)``."""
    i0, j0, i1, j1 = box
    x = (np.arange(i0, i1) + 0.5) * v
    y = (np.arange(j0, j1) + 0.5) * v
    xx, yy = np.meshgrid(x, y)
    return bilinear_height(reference.heights_mm, reference.cell_mm,
                           np.column_stack([xx.ravel(), yy.ravel()])).reshape(len(y), len(x))


def _reference_distance(hw, v, ii, jj, z) -> np.ndarray:
    """``(z - h) * n_z`` at window columns ``(ii, jj)``: height above the reference projected
    on its normal [mm]; ``hw`` (ny, nx) the reference at the window's voxel columns."""
    if hw.shape[0] > 1 and hw.shape[1] > 1:
        gy, gx = np.gradient(hw, v)
        g2 = gx[jj, ii] ** 2 + gy[jj, ii] ** 2
    else:
        g2 = 0.0
    return (z - hw[jj, ii]) / np.sqrt(1.0 + g2)
