"""Numba kernels of the real-time deviation (:mod:`dm2.realtime`).

One frame set's comparison is a handful of small arrays (a 24 x 24 column window at 0.5 mm
voxels). As numpy calls it took about 2 ms of CPU but 5-30 ms of wall time on a live run: numpy
releases the interpreter lock in every call on more than a few hundred elements, and on a busy
live process (socket, recorder and analysis threads) each release could wait up to a switch
interval to take it back. Here the whole comparison is one compiled call that holds the lock
throughout and runs in well under a millisecond. The arithmetic is numpy's, operation for
operation (bilinear heights as :func:`dm2.refmap.bilinear_height`, slopes as ``np.gradient``).
"""

from __future__ import annotations

import numpy as np
from numba import njit

OVER, UNDER = 1, 2


@njit(cache=True)
def column_crossings(d, w, min_weight):
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


@njit(cache=True)
def window_reference_heights(heights_mm, cell_mm, i0, j0, i1, j1, voxel_mm):
    """Reference heights [mm] (ny, nx) at the voxel column centres ``i0:i1, j0:j1``: bilinear
    in the cell-centred grid ``heights_mm`` (as :func:`dm2.refmap.bilinear_height`)."""
    gny, gnx = heights_mm.shape
    out = np.empty((j1 - j0, i1 - i0))
    for jj in range(j1 - j0):
        y = (j0 + jj + 0.5) * voxel_mm
        fy = min(max(y / cell_mm - 0.5, 0.0), gny - 1.0)
        cj = min(np.int64(fy), gny - 2)
        ty = fy - cj
        for ii in range(i1 - i0):
            x = (i0 + ii + 0.5) * voxel_mm
            fx = min(max(x / cell_mm - 0.5, 0.0), gnx - 1.0)
            ci = min(np.int64(fx), gnx - 2)
            tx = fx - ci
            out[jj, ii] = ((1 - tx) * (1 - ty) * heights_mm[cj, ci]
                           + tx * (1 - ty) * heights_mm[cj, ci + 1]
                           + (1 - tx) * ty * heights_mm[cj + 1, ci]
                           + tx * ty * heights_mm[cj + 1, ci + 1])
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
                    deviation_map, flag_map, first_flag_s, alarmed):
    """Compare a dense TSDF box with the reference and update the column maps in place.

    ``d, w (nx, ny, nz)``: the box's signed distance [mm] and weight, voxel ``(i0, j0, k0)`` at
    index 0; ``hw (ny, nx)``: the reference [mm] at its columns. Each column with an observed
    zero crossing inside the maps gets its deviation: height above the reference projected on
    the reference normal, ``(z - h) / sqrt(1 + |grad h|^2)`` [mm]; beyond ``+-delta_mm`` it is
    flagged over (1) or under (2). Returns ``gi, gj`` (map column indices), ``dev`` [mm] and
    ``flag`` of those columns, in ``np.nonzero`` order, and how many columns were newly flagged
    (flag changed to over or under).
    """
    cross = column_crossings(d, w, min_weight)
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
            e = (z - hw[jj, ii]) / np.sqrt(1.0 + g2)
            f = OVER if e > delta_mm else (UNDER if e < -delta_mm else 0)
            deviation_map[y, x] = e
            if f != 0 and flag_map[y, x] != f:
                first_flag_s[y, x] = stamp_s
                newly += 1
            flag_map[y, x] = f
            if f == 0:
                alarmed[y, x] = False
            gi[n], gj[n], dev[n], flag[n] = x, y, e, f
            n += 1
    return gi[:n], gj[:n], dev[:n], flag[:n], newly
