"""Numba kernels of the real-time deviation (:mod:`dm2.defects.realtime`).

One frame set's comparison is a handful of small arrays (a 24 x 24 column window at 0.5 mm
voxels). As numpy calls it took about 2 ms of CPU but 5-30 ms of wall time on a live run: numpy
releases the interpreter lock in every call on more than a few hundred elements, and on a busy
live process (socket, recorder and analysis threads) each release could wait up to a switch
interval to take it back. Here the whole comparison is one compiled call that holds the lock
throughout and runs in well under a millisecond. The arithmetic is numpy's, operation for
operation (bilinear heights by :func:`dm2.reference.height_map.bilinear_at`, slopes as
``np.gradient``).
The alarm patches (:func:`patch_alarms`) are likewise one call: the closing and 8-connected
labelling of ``scipy.ndimage`` (``binary_closing``, ``label``), with the same result.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from dm2.defects.classify import LOCAL_CURVATURE_RADIUS_MM
from dm2.defects.uncertainty import EDGE_RADIUS_MM, HEIGHT_SCALE_MM
from dm2.reference.height_map import bilinear_at

OVER, UNDER = 1, 2


@njit(cache=True)
def column_crossings(d, w, min_weight):
    """Fractional voxel index (nx, ny) of the topmost - to + crossing along z, NaN if none."""
    return column_crossings_weights(d, w, min_weight)[0]


@njit(cache=True)
def column_crossings_weights(d, w, min_weight):
    """:func:`column_crossings` and the smaller TSDF weight of the two voxels bracketing each
    crossing (nx, ny) (0 where none)."""
    nx, ny, nz = d.shape
    out = np.full((nx, ny), np.nan)
    wc = np.zeros((nx, ny))
    for i in range(nx):
        for j in range(ny):
            for k in range(nz - 2, -1, -1):
                if w[i, j, k] < min_weight or w[i, j, k + 1] < min_weight:
                    continue
                a, b = d[i, j, k], d[i, j, k + 1]
                if a < 0.0 <= b:
                    out[i, j] = k + (-a) / (b - a)
                    wc[i, j] = min(w[i, j, k], w[i, j, k + 1])
                    break
    return out, wc


@njit(cache=True)
def window_reference_heights(heights_mm, cell_mm, i0, j0, i1, j1, voxel_mm):
    """Reference heights [mm] (ny, nx) at the voxel column centres ``i0:i1, j0:j1``: bilinear
    in the cell-centred grid ``heights_mm`` (:func:`dm2.reference.height_map.bilinear_at`)."""
    out = np.empty((j1 - j0, i1 - i0))
    for jj in range(j1 - j0):
        y = (j0 + jj + 0.5) * voxel_mm
        for ii in range(i1 - i0):
            out[jj, ii] = bilinear_at(heights_mm, cell_mm, (i0 + ii + 0.5) * voxel_mm, y)
    return out


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


@njit(cache=True)
def compare_columns(d, w, min_weight, i0, j0, k0, hw, voxel_mm, delta_mm, stamp_s,
                    deviation_map, flag_map, first_flag_s, alarmed, flag_count=None,
                    bound=(0.0, 0.0, 0.0, 0.0, 0.0), weight_map=None, strong_map=None,
                    measured_map=None, expected_map=None, curvature=None, edge_mm=0.0,
                    laplacian=None, plume_mm2=0.0):
    """Compare a dense TSDF box with the reference and update the column maps in place.

    ``d, w (nx, ny, nz)``: the box's signed distance [mm] and weight, voxel ``(i0, j0, k0)`` at
    index 0; ``hw (ny, nx)``: the reference [mm] at its columns. Each column with an observed
    zero crossing inside the maps gets its deviation: height above the reference projected on
    the reference normal, ``(z - h) / sqrt(1 + |grad h|^2)`` [mm]; beyond ``+-delta_mm`` it is
    flagged over (1) or under (2), and marked in ``strong_map`` where beyond the confidence
    bound ``k * sigma`` too, with ``bound
    = (k, floor_mm, range_mm, wall_mm, height_mm)`` and ``sigma^2 = floor^2 + range^2 / weight +
    (wall * (1 - n_z))^2 + (height * h / HEIGHT_SCALE_MM)^2`` (the column's weight at its
    crossing; ``n_z`` and the height ``h`` of the reference there; the terms of
    :mod:`dm2.defects.uncertainty` but the foot and gap, which default to zero; the edge term
    with ``curvature``, below).
    ``flag_count`` counts each column's observations in a row with the same flag, an observation
    being a comparison whose crossing weight (kept in ``weight_map``) or deviation changed since
    the last: new measurement, not the same TSDF compared again. Returns ``gi, gj`` (map column
    indices), ``dev`` [mm] and ``flag`` of those columns, in ``np.nonzero`` order, and how many
    columns were newly flagged (flag changed to over or under) or, with ``flag_count``, observed
    flagged again.

    With ``measured_map`` and ``expected_map`` (and ``weight_map``) the comparison follows the
    measurement, not the reference: an observation is a comparison whose measured crossing
    (height, kept in ``measured_map``, or weight) changed since the last; a column compared
    again without one keeps its deviation and flag (the reference has grown over a surface
    measured before: no new evidence). The measured height is a running average of the
    column's observations (the TSDF's weights), so while deposition goes on over the column it
    lags the surface; the reference only grows, so the measurement of a part that follows it
    lies between the reference at the column's previous observation (kept in
    ``expected_map``) and the reference now. The deviation is the distance beyond that
    interval: overbuild above the reference now, underbuild below the reference as it stood at
    the previous observation, zero inside. Once the deposition over a column has ended the
    interval closes and the deviation is the plain one.

    With ``curvature`` (ny, nx) [1/mm], the reference's mean curvature at the columns
    (:func:`dm2.defects.realtime_curvature.window_mean_curvature`), the bound holds the edge
    term of :mod:`dm2.defects.uncertainty` too, ``edge_mm * min(1, max(0, |H| - 1 /
    LOCAL_CURVATURE_RADIUS_MM) * EDGE_RADIUS_MM)``: the Gaussian model's known mismatch at the
    reference's rounded edges and corners, as the layer analysis judges them. With
    ``laplacian`` (ny, nx) [1/mm] of the same smoothed reference it holds the plume term too,
    ``plume_mm2 * laplacian`` with ``plume_mm2 = plume_rel * sigma^2``: how far the reference
    moves when its plume width is off by ``plume_rel``.
    """
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
            if measured_map is not None:
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
                if curvature is not None:
                    excess = max(abs(curvature[jj, ii]) - 1.0 / LOCAL_CURVATURE_RADIUS_MM, 0.0)
                    edge = edge_mm * min(1.0, excess * EDGE_RADIUS_MM)
                plume = plume_mm2 * laplacian[jj, ii] if laplacian is not None else 0.0
                sig = np.sqrt(fl2 + rg2 / max(wcross[ii, jj], 1.0) + wl2 * tilt * tilt
                              + hgt * hgt + edge * edge + plume * plume)
                lim = kb * sig
            f = OVER if e > delta_mm else (UNDER if e < -delta_mm else 0)
            if strong_map is not None:
                strong_map[y, x] = f != 0 and abs(e) > lim
            fresh = True
            if weight_map is not None:
                fresh = (measured_map is not None or wcross[ii, jj] != weight_map[y, x]
                         or e != deviation_map[y, x])
                weight_map[y, x] = wcross[ii, jj]
            deviation_map[y, x] = e
            if f != 0 and flag_map[y, x] != f:
                first_flag_s[y, x] = stamp_s
                newly += 1
            elif f != 0 and fresh and flag_count is not None:
                newly += 1  # observed flagged again: the column's evidence grew
            if flag_count is not None:
                if f == 0:
                    flag_count[y, x] = 0
                elif flag_map[y, x] == f:
                    if fresh:
                        flag_count[y, x] += 1
                else:
                    flag_count[y, x] = 1
            flag_map[y, x] = f
            if f == 0:
                alarmed[y, x] = False
            gi[n], gj[n], dev[n], flag[n] = x, y, e, f
            n += 1
    return gi[:n], gj[:n], dev[:n], flag[:n], newly


@njit(cache=True)
def patch_alarms(flags, kind, deviation_mm, alarmed, first_flag_s, link, min_cells,
                 mature=None):
    """New alarms of one kind in a window of the column maps, marking their columns alarmed.

    The columns flagged ``kind`` (``hit``), bridged over unobserved columns (deviation NaN:
    ``unseen``) by a closing with the disk ``link`` (dilation then erosion, outside the window
    counting as not flagged; never over observed-normal columns:
    ``(closing & (hit | unseen)) | hit``), form 8-connected patches, numbered in raster order.
    Each patch of at least ``min_cells`` columns that holds a flagged column and no alarmed one
    raises an alarm (an island of bridged unobserved columns cut off from the flagged ones by
    observed-normal columns shows no defect); with ``mature`` (bool, like ``flags``) the patch
    must hold a flagged column that is mature (persistent) too. Returns per alarm, in patch
    order: its size [columns], the mean row and column of its columns and the earliest
    first-flag stamp [s] among them.
    """
    hit = flags == kind
    if not hit.any():
        return np.zeros(0, np.int64), np.zeros((0, 3))
    patch = _bridged_patch(hit, np.isnan(deviation_mm), link)
    labels, n = _label_8_connected(patch)
    size, rows, cols, first, taken, flagged = _patch_sums(labels, n, hit, alarmed, first_flag_s,
                                                          mature)
    raise_ = np.zeros(n + 1, np.bool_)
    for lab in range(1, n + 1):
        raise_[lab] = size[lab] >= min_cells and flagged[lab] and not taken[lab]
    _mark_alarmed(labels, raise_, alarmed)
    return _alarm_rows(raise_, size, rows, cols, first)


@njit(cache=True)
def _dilate(hit, link):
    """(h, w) bool: ``hit`` dilated by the disk ``link`` (odd square of bools), clipped."""
    h, w = hit.shape
    r = link.shape[0] // 2
    dil = np.zeros((h, w), np.bool_)
    for y in range(h):
        for x in range(w):
            if hit[y, x]:
                for a in range(-r, r + 1):
                    for b in range(-r, r + 1):
                        yy, xx = y + a, x + b
                        if link[a + r, b + r] and 0 <= yy < h and 0 <= xx < w:
                            dil[yy, xx] = True
    return dil


@njit(cache=True)
def _disk_inside(dil, link, y, x):
    """The disk ``link`` centred on ``(y, x)`` lies inside ``dil`` (outside the window does
    not count as inside): the erosion of ``dil`` at that column."""
    h, w = dil.shape
    r = link.shape[0] // 2
    for a in range(-r, r + 1):
        for b in range(-r, r + 1):
            yy, xx = y + a, x + b
            if link[a + r, b + r] and not (0 <= yy < h and 0 <= xx < w and dil[yy, xx]):
                return False
    return True


@njit(cache=True)
def _bridged_patch(hit, unseen, link):
    """(h, w) bool: ``(closing(hit, link) & (hit | unseen)) | hit``: the flagged columns and
    the unobserved ones that the closing bridges."""
    h, w = hit.shape
    dil = _dilate(hit, link)
    patch = np.zeros((h, w), np.bool_)
    for y in range(h):
        for x in range(w):
            if hit[y, x]:
                patch[y, x] = True
            elif unseen[y, x] and dil[y, x]:
                patch[y, x] = _disk_inside(dil, link, y, x)
    return patch


@njit(cache=True)
def _flood_label(patch, labels, stack, y, x, n):
    """Give label ``n`` to the 8-connected patch of ``patch`` holding ``(y, x)`` (depth
    first, ``stack`` as scratch)."""
    h, w = patch.shape
    labels[y, x] = n
    stack[0, 0], stack[0, 1] = y, x
    top = 1
    while top:
        top -= 1
        cy, cx = stack[top, 0], stack[top, 1]
        for a in range(-1, 2):
            for b in range(-1, 2):
                yy, xx = cy + a, cx + b
                if 0 <= yy < h and 0 <= xx < w and patch[yy, xx] and labels[yy, xx] == 0:
                    labels[yy, xx] = n
                    stack[top, 0], stack[top, 1] = yy, xx
                    top += 1


@njit(cache=True)
def _label_8_connected(patch):
    """8-connected labels (h, w) int64 of ``patch``, 1.. in raster order of each patch's first
    column (0 outside), and their count (``scipy.ndimage.label`` with a full structure)."""
    h, w = patch.shape
    labels = np.zeros((h, w), np.int64)
    stack = np.empty((h * w, 2), np.int64)
    n = 0
    for y in range(h):
        for x in range(w):
            if patch[y, x] and labels[y, x] == 0:
                n += 1
                _flood_label(patch, labels, stack, y, x, n)
    return labels, n


@njit(cache=True)
def _patch_sums(labels, n, hit, alarmed, first_flag_s, mature):
    """Per label 0..n: column count, sum of rows and of columns, earliest first-flag stamp
    [s] (NaN if none), whether it holds an alarmed column, and whether it holds a flagged one
    (mature too, with ``mature``)."""
    h, w = labels.shape
    size = np.zeros(n + 1, np.int64)
    taken = np.zeros(n + 1, np.bool_)
    flagged = np.zeros(n + 1, np.bool_)
    rows = np.zeros(n + 1)
    cols = np.zeros(n + 1)
    first = np.full(n + 1, np.nan)
    for y in range(h):
        for x in range(w):
            lab = labels[y, x]
            if lab:
                size[lab] += 1
                rows[lab] += y
                cols[lab] += x
                if alarmed[y, x]:
                    taken[lab] = True
                if hit[y, x] and (mature is None or mature[y, x]):
                    flagged[lab] = True
                f = first_flag_s[y, x]
                if not np.isnan(f) and not f >= first[lab]:
                    first[lab] = f
    return size, rows, cols, first, taken, flagged


@njit(cache=True)
def _mark_alarmed(labels, raise_, alarmed):
    """Mark alarmed every column whose label raises an alarm."""
    h, w = labels.shape
    for y in range(h):
        for x in range(w):
            if raise_[labels[y, x]]:
                alarmed[y, x] = True


@njit(cache=True)
def _alarm_rows(raise_, size, rows, cols, first):
    """Per raised label, in label order: its size [columns] and (mean row, mean column,
    earliest first-flag stamp [s])."""
    m = 0
    for lab in range(1, raise_.shape[0]):
        if raise_[lab]:
            m += 1
    out_n = np.empty(m, np.int64)
    out_f = np.empty((m, 3))
    k = 0
    for lab in range(1, raise_.shape[0]):
        if raise_[lab]:
            out_n[k] = size[lab]
            out_f[k, 0] = rows[lab] / size[lab]
            out_f[k, 1] = cols[lab] / size[lab]
            out_f[k, 2] = first[lab]
            k += 1
    return out_n, out_f
