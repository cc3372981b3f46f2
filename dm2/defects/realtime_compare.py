"""The real-time comparison of one frame set's TSDF box with the reference
(:mod:`dm2.defects.realtime`): one compiled call over the box's voxel columns, its arguments
bundled: :class:`ReferenceWindow`, :class:`ColumnMaps` and :class:`CompareParams` name the
fields of each bundle.

From Python the bundles go as plain tuples of those fields, in their order: numba types a
named tuple argument about 0.6 us slower than a plain one (its fingerprint is not on the fast
path that arrays, scalars and plain tuples take), and the three cost a frame set's call 2.5 us
against 3.1 us for all of it with 24 flat arguments or 3 plain tuples. The kernel unpacks
either kind the same way.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit

from dm2.defects.classify import LOCAL_CURVATURE_RADIUS_MM
from dm2.defects.realtime_kernels import OVER, UNDER, column_crossings_weights
from dm2.defects.uncertainty import EDGE_RADIUS_MM, HEIGHT_SCALE_MM

NO_WINDOW_TERMS = np.zeros((0, 0))  # ReferenceWindow.curvature_per_mm/laplacian_per_mm: none


class ColumnMaps(NamedTuple):
    """The monitor's persistent maps over the plate's voxel columns, each ``(ny, nx)``: row
    ``y``, column ``x`` is the column centred at ``((x + 0.5) v, (y + 0.5) v)`` [mm, O] (``v``
    the voxel edge). Updated in place by :func:`compare_columns`."""

    deviation_mm: np.ndarray  # float64 [mm], last deviation (NaN: never observed)
    flag: np.ndarray  # int8, 0 normal, OVER (1) or UNDER (2)
    first_flag_s: np.ndarray  # float64 [s], stamp at which the column took its current flag
    alarmed: np.ndarray  # bool, the column belongs to a patch that raised an alarm
    flag_count: np.ndarray  # int64, observations in a row with the same flag
    weight: np.ndarray  # float64, TSDF weight of the crossing at the last observation
    strong: np.ndarray  # bool, flagged and beyond the confidence bound
    measured_mm: np.ndarray  # float64 [mm, O], measured crossing height at the last observation
    expected_mm: np.ndarray  # float64 [mm, O], the reference there at the last observation
    overspray: np.ndarray  # bool, read only: on the plate outside the outline, never strong


class ReferenceWindow(NamedTuple):
    """The reference at the voxel columns of one TSDF box, the arrays ``(ny, nx)`` (row:
    ``y``)."""

    heights_mm: np.ndarray  # float64 [mm, O], reference heights (bilinear at column centres)
    curvature_per_mm: np.ndarray  # float64 [1/mm], mean curvature (+ convex); or
    # NO_WINDOW_TERMS, then the bound holds neither the edge nor the plume term
    laplacian_per_mm: np.ndarray  # float64 [1/mm], laplacian of the same smoothed reference;
    # or NO_WINDOW_TERMS, with curvature_per_mm
    plume_mm2: float  # [mm^2] plume term's scale: plume_rel * sigma^2 of this reference's plume


class CompareParams(NamedTuple):
    """The constants of the comparisons of one monitor."""

    min_weight: np.float32  # TSDF weight both voxels bracketing a crossing must reach
    voxel_mm: float  # [mm] voxel edge
    delta_mm: float  # [mm] tolerance: a deviation beyond +-delta_mm is flagged
    bound: tuple  # (k, floor_mm, range_mm, wall_mm, height_mm) of the confidence bound
    # k * sigma (k = 0: no bound; terms of dm2.defects.uncertainty)
    edge_mm: float  # [mm] edge term's scale (dm2.defects.uncertainty)


@njit(cache=True, inline="always")
def _slope(h, a, n, v, along_rows, fixed):
    """``np.gradient`` of ``h`` along one axis at index ``a`` of ``n`` (spacing ``v``)."""
    if along_rows:
        if a == 0:
            return (h[1, fixed] - h[0, fixed]) / v
        if a == n - 1:
            return (h[n - 1, fixed] - h[n - 2, fixed]) / v
        return (h[a + 1, fixed] - h[a - 1, fixed]) / (2.0 * v)
    if a == 0:
        return (h[fixed, 1] - h[fixed, 0]) / v
    if a == n - 1:
        return (h[fixed, n - 1] - h[fixed, n - 2]) / v
    return (h[fixed, a + 1] - h[fixed, a - 1]) / (2.0 * v)


@njit(cache=True, nogil=True)
def compare_columns(d, w, origin_voxel, window, maps, params, stamp_s):
    """Compare a dense TSDF box with the reference and update the column maps in place.

    ``d, w (nx, ny, nz)`` float32: the box's signed distance [mm] and weight, voxel
    ``origin_voxel = (i0, j0, k0)`` at index 0; ``window``: the :class:`ReferenceWindow` at
    its columns; ``maps``: the :class:`ColumnMaps`; ``params``: the :class:`CompareParams`
    (each as a plain tuple of its fields from Python, see the module's docstring);
    ``stamp_s`` [s] the frame set's stamp. Each column with an observed zero crossing inside
    the maps gets its deviation: height above the reference projected on the reference normal,
    ``(z - h) / sqrt(1 + |grad h|^2)`` [mm]; beyond ``+-delta_mm`` it is flagged over (1) or
    under (2), and marked in ``maps.strong`` where beyond the confidence bound ``k * sigma``
    too, with ``bound = (k, floor_mm, range_mm, wall_mm, height_mm)`` and ``sigma^2 = floor^2
    + range^2 / weight + (wall * (1 - n_z))^2 + (height * h / HEIGHT_SCALE_MM)^2`` (the
    column's weight at its crossing; ``n_z`` and the height ``h`` of the reference there; the
    terms of :mod:`dm2.defects.uncertainty` but the foot and gap, which default to zero; the
    edge and plume terms with the window's curvature, below).

    The comparison follows the measurement, not the reference: an observation is a comparison
    whose measured crossing (height, kept in ``maps.measured_mm``, or weight, in
    ``maps.weight``) changed since the last; a column compared again without one keeps its
    deviation and flag (the reference has grown over a surface measured before: no new
    evidence). ``maps.flag_count`` counts each column's observations in a row with the same
    flag. The measured height is a running average of the column's observations (the TSDF's
    weights), so while deposition goes on over the column it lags the surface; the reference
    only grows, so the measurement of a part that follows it lies between the reference at the
    column's previous observation (kept in ``maps.expected_mm``) and the reference now. The
    deviation is the distance beyond that interval: overbuild above the reference now,
    underbuild below the reference as it stood at the previous observation, zero inside. Once
    the deposition over a column has ended the interval closes and the deviation is the plain
    one. Returns ``gi, gj`` (map column indices), ``dev`` [mm] and ``flag`` of those columns,
    in ``np.nonzero`` order, and how many columns were newly flagged (flag changed to over or
    under) or observed flagged again.

    With the window's ``curvature_per_mm``
    (:func:`dm2.defects.realtime_curvature.window_curvatures`), the bound holds the edge term
    of :mod:`dm2.defects.uncertainty` too, ``edge_mm * min(1, max(0, |H| - 1 /
    LOCAL_CURVATURE_RADIUS_MM) * EDGE_RADIUS_MM)``: the Gaussian model's known mismatch at the
    reference's rounded edges and corners, as the layer analysis judges them; with its
    ``laplacian_per_mm`` the plume term too, ``plume_mm2 * laplacian`` with ``plume_mm2 =
    plume_rel * sigma^2``: how far the reference moves when its plume width is off by
    ``plume_rel``.
    """
    i0, j0, k0 = origin_voxel
    hw, curvature, laplacian, plume_mm2 = window
    deviation_map, flag_map, first_flag_s, alarmed, flag_count, weight_map, strong_map, \
        measured_map, expected_map, overspray = maps
    min_weight, voxel_mm, delta_mm, bound, edge_mm = params
    with_curvature = curvature.shape[0] > 0
    with_laplacian = laplacian.shape[0] > 0
    cross, wcross = column_crossings_weights(d, w, min_weight)
    kb, fl2, rg2, wl2 = bound[0], bound[1] ** 2, bound[2] ** 2, bound[3] ** 2
    ht = bound[4]
    nx, ny = cross.shape
    mny, mnx = flag_map.shape
    hy, hx = hw.shape
    slopes = hy > 1 and hx > 1
    n = 0
    newly = 0
    gi = np.empty(nx * ny, np.int64)
    gj = np.empty(nx * ny, np.int64)
    dev = np.empty(nx * ny)
    flag = np.empty(nx * ny, np.int8)
    for ii in range(nx):
        for jj in range(ny):
            c = cross[ii, jj]
            x, y = ii + i0, jj + j0
            if not np.isfinite(c) or x < 0 or x >= mnx or y < 0 or y >= mny:
                continue
            z = (k0 + c + 0.5) * voxel_mm
            if slopes:
                gx = _slope(hw, ii, hx, voxel_mm, False, jj)
                gy = _slope(hw, jj, hy, voxel_mm, True, ii)
                g2 = gx ** 2 + gy ** 2
            else:
                g2 = 0.0
            target = hw[jj, ii]
            wo, wn = weight_map[y, x], wcross[ii, jj]
            if wn == wo and z == measured_map[y, x]:  # the same TSDF compared again
                gi[n], gj[n], dev[n], flag[n] = x, y, deviation_map[y, x], flag_map[y, x]
                n += 1
                continue
            r = expected_map[y, x]
            lo = min(r, target) if wo > 0.0 and np.isfinite(r) else target
            expected_map[y, x] = target
            measured_map[y, x] = z
            if z < lo:  # below the reference as it stood at the previous observation
                target = lo
            elif z <= target:  # within the lag: no deviation
                target = z
            e = (z - target) / np.sqrt(1.0 + g2)
            lim = 0.0
            if kb > 0.0:
                tilt = 1.0 - 1.0 / np.sqrt(1.0 + g2)
                hgt = ht * max(hw[jj, ii], 0.0) / HEIGHT_SCALE_MM
                edge = 0.0
                if with_curvature:
                    excess = max(abs(curvature[jj, ii]) - 1.0 / LOCAL_CURVATURE_RADIUS_MM, 0.0)
                    edge = edge_mm * min(1.0, excess * EDGE_RADIUS_MM)
                plume = plume_mm2 * laplacian[jj, ii] if with_laplacian else 0.0
                sig = np.sqrt(fl2 + rg2 / max(wcross[ii, jj], 1.0) + wl2 * tilt * tilt
                              + hgt * hgt + edge * edge + plume * plume)
                lim = kb * sig
            f = OVER if e > delta_mm else (UNDER if e < -delta_mm else 0)
            strong_map[y, x] = f != 0 and abs(e) > lim and not overspray[y, x]
            weight_map[y, x] = wcross[ii, jj]
            deviation_map[y, x] = e
            if f != 0 and flag_map[y, x] != f:
                first_flag_s[y, x] = stamp_s
                newly += 1
            elif f != 0:
                newly += 1  # observed flagged again: the column's evidence grew
            if f == 0:
                flag_count[y, x] = 0
            elif flag_map[y, x] == f:
                flag_count[y, x] += 1
            else:
                flag_count[y, x] = 1
            flag_map[y, x] = f
            if f == 0:
                alarmed[y, x] = False
            gi[n], gj[n], dev[n], flag[n] = x, y, e, f
            n += 1
    return gi[:n], gj[:n], dev[:n], flag[:n], newly
