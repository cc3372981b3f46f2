"""Neighbouring profile points fused as one ray (paper eqs 2-5, at the field's resolution).

A 2D laser profiler samples its line far finer than the TSDF resolves: the twin's and common
scanCONTROL heads give 640 points over 50 mm, one every 0.08 mm, against 0.5 mm voxels. Each
point walks its own ray through the same few voxels as its neighbours, so the fusion spent most
of its time writing the same voxels over again.

:func:`merge_profile_points` replaces each run of consecutive points of a profile that lie
within ``span_mm`` of the run's first point, along the line (``x``) and in range (``z``), by
their mean, with the number of points as its count. The kernels update each voxel on that ray
as many times as it has points (:func:`dm2.fusion.tsdf.ray_walk.update_voxel`, with the weight
caps applied at each update as for a point), so a voxel ends with the same weight as with the
points one by one, and with their signed distances' running mean to first order, at the caps
too. With ``span_mm`` half a voxel (``[monitor] ray_merge_voxels =
0.5``; the package default is 0, every point its own ray, see the README for why) a run never
spans more than that: an edge, a step or a wall seen at a grazing angle changes the range
between neighbours by more and ends the run, and the mean of a run lies on the surface its
points saw. A point's own noise averages out within its run (the static accuracy of
``benchmarks/fusion.py`` improves, see the README).
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def merge_profile_points(xz_S, offsets, span_mm):
    """``(xz (m, 2), offsets (k + 1,), count (m,) int64)``: the profiles ``xz_S[offsets[j]:
    offsets[j + 1]]`` (float64 [mm, S], in order along the line) with each run of consecutive
    points within ``span_mm`` of its first point in ``x`` and in ``z`` replaced by the run's
    mean and its number of points (``span_mm <= 0``: every point alone, count 1)."""
    n = xz_S.shape[0]
    out = np.empty((n, 2))
    count = np.empty(n, dtype=np.int64)
    new_offsets = np.empty_like(offsets)
    new_offsets[0] = 0
    m = 0
    for p in range(offsets.shape[0] - 1):
        i, end = offsets[p], offsets[p + 1]
        while i < end:
            x0, z0 = xz_S[i, 0], xz_S[i, 1]
            sx, sz = x0, z0
            j = i + 1
            while j < end and abs(xz_S[j, 0] - x0) <= span_mm and abs(xz_S[j, 1] - z0) <= span_mm:
                sx += xz_S[j, 0]
                sz += xz_S[j, 1]
                j += 1
            c = j - i
            out[m, 0] = sx / c
            out[m, 1] = sz / c
            count[m] = c
            m += 1
            i = j
        new_offsets[p + 1] = m
    return out[:m].copy(), new_offsets, count[:m].copy()
