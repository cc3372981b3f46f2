"""The reference's mean curvature and Laplacian at the real-time window's voxel columns (numba).

The layer analysis gives a deviation at a rounded edge or corner of the reference its larger
uncertainty (the ``edge`` term of :mod:`dm2.defects.uncertainty`), from the reference's mean
curvature after a Gaussian smoothing of ``smooth_mm``
(:meth:`dm2.reference.height_map.ReferenceMap.mean_curvature_at` on the reference sampled at
the voxel columns). The real-time comparison takes the same term from this kernel: the
reference sampled at the voxel column centres of the window and a margin around it, smoothed
(the separable Gaussian of ``scipy.ndimage.gaussian_filter``, truncated at 4 sigma), then the
derivatives as ``np.gradient`` and the curvature of the height field. Inside the plate, the
margin makes the window's values those of the whole map (``tests/test_realtime_curvature.py``
checks them against the scipy statement). The Laplacian ``hxx + hyy`` of the same smoothed
field gives the plume term (``sigma^2 laplacian(h)``,
:meth:`dm2.reference.height_map.ReferenceMap.plume_sensitivity_at`).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from dm2.reference.height_map import bilinear_at

SMOOTH_MM = 0.75  # as ReferenceMap.mean_curvature_at's default


@njit(cache=True)
def _gauss_weights(sigma):
    r = int(4.0 * sigma + 0.5)
    w = np.empty(2 * r + 1)
    s = 0.0
    for k in range(-r, r + 1):
        w[k + r] = np.exp(-0.5 * k * k / (sigma * sigma))
        s += w[k + r]
    return w / s, r


@njit(cache=True)
def _smooth_axis(a, w, r, axis):
    ny, nx = a.shape
    out = np.empty_like(a)
    for y in range(ny):
        for x in range(nx):
            acc = 0.0
            for k in range(-r, r + 1):
                if axis == 0:
                    yy = min(max(y + k, 0), ny - 1)
                    acc += w[k + r] * a[yy, x]
                else:
                    xx = min(max(x + k, 0), nx - 1)
                    acc += w[k + r] * a[y, xx]
            out[y, x] = acc
    return out


@njit(cache=True)
def _grad(a, v, axis):
    """``np.gradient(a, v)`` along ``axis`` (second-order inside, first-order at the ends)."""
    ny, nx = a.shape
    g = np.empty_like(a)
    for y in range(ny):
        for x in range(nx):
            if axis == 0:
                if y == 0:
                    g[y, x] = (a[1, x] - a[0, x]) / v
                elif y == ny - 1:
                    g[y, x] = (a[ny - 1, x] - a[ny - 2, x]) / v
                else:
                    g[y, x] = (a[y + 1, x] - a[y - 1, x]) / (2.0 * v)
            else:
                if x == 0:
                    g[y, x] = (a[y, 1] - a[y, 0]) / v
                elif x == nx - 1:
                    g[y, x] = (a[y, nx - 1] - a[y, nx - 2]) / v
                else:
                    g[y, x] = (a[y, x + 1] - a[y, x - 1]) / (2.0 * v)
    return g


@njit(cache=True, nogil=True)
def window_curvatures(heights_mm, cell_mm, i0, j0, i1, j1, voxel_mm, nx_map, ny_map,
                      smooth_mm=SMOOTH_MM):
    """``(mean curvature [1/mm], laplacian [1/mm])``, each (j1 - j0, i1 - i0), of the reference
    at the voxel columns ``i0:i1, j0:j1`` (curvature + where convex), the voxel-column grid
    being ``nx_map x ny_map``."""
    w, r = _gauss_weights(smooth_mm / voxel_mm)
    p = r + 2
    a0, b0 = max(i0 - p, 0), max(j0 - p, 0)
    a1, b1 = min(i1 + p, nx_map), min(j1 + p, ny_map)
    out = np.zeros((j1 - j0, i1 - i0))
    lap = np.zeros((j1 - j0, i1 - i0))
    if b1 - b0 < 2 or a1 - a0 < 2:
        return out, lap
    h = np.empty((b1 - b0, a1 - a0))
    for jj in range(b1 - b0):
        y = (b0 + jj + 0.5) * voxel_mm
        for ii in range(a1 - a0):
            h[jj, ii] = bilinear_at(heights_mm, cell_mm, (a0 + ii + 0.5) * voxel_mm, y)
    s = _smooth_axis(_smooth_axis(h, w, r, 0), w, r, 1)
    hy, hx = _grad(s, voxel_mm, 0), _grad(s, voxel_mm, 1)
    hxy, hxx, hyy = _grad(hx, voxel_mm, 0), _grad(hx, voxel_mm, 1), _grad(hy, voxel_mm, 0)
    for jj in range(j1 - j0):
        for ii in range(i1 - i0):
            y, x = j0 + jj - b0, i0 + ii - a0
            if y < 0 or y >= s.shape[0] or x < 0 or x >= s.shape[1]:  # off the plate
                continue
            gx, gy = hx[y, x], hy[y, x]
            num = ((1 + gy * gy) * hxx[y, x] - 2 * gx * gy * hxy[y, x]
                   + (1 + gx * gx) * hyy[y, x])
            out[jj, ii] = -num / (2.0 * (1 + gx * gx + gy * gy) ** 1.5)
            lap[jj, ii] = hxx[y, x] + hyy[y, x]
    return out, lap


def window_mean_curvature(heights_mm, cell_mm, i0, j0, i1, j1, voxel_mm, nx_map, ny_map,
                          smooth_mm=SMOOTH_MM):
    """Mean curvature [1/mm] (j1 - j0, i1 - i0) of the reference at the voxel columns
    ``i0:i1, j0:j1`` (+ where convex), the voxel-column grid being ``nx_map x ny_map``."""
    return window_curvatures(heights_mm, cell_mm, i0, j0, i1, j1, voxel_mm, nx_map, ny_map,
                             smooth_mm)[0]
