"""Numba kernels of the real-time deviation (:mod:`dm2.defects.realtime`).

One frame set's comparison is a handful of small arrays (a 24 x 24 column window at 0.5 mm
voxels). As numpy calls it took about 2 ms of CPU but 5-30 ms of wall time on a live run: numpy
releases the interpreter lock in every call on more than a few hundred elements, and on a busy
live process (socket, recorder and analysis threads) each release could wait up to a switch
interval to take it back. Here the whole comparison is one compiled call that holds the lock
throughout and runs in well under a millisecond
(:func:`dm2.defects.realtime_compare.compare_columns`, over the crossings found here). The
arithmetic is numpy's, operation for operation (bilinear heights by
:func:`dm2.reference.height_map.bilinear_at`, slopes as ``np.gradient``).
The alarm patches (:func:`patch_alarms`) are likewise one call: the closing and 8-connected
labelling of ``scipy.ndimage`` (``binary_closing``, ``label``), with the same result.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from dm2.reference.height_map import bilinear_at

OVER, UNDER = 1, 2


@njit(cache=True, nogil=True)
def column_crossings(d, w, min_weight):
    """Fractional voxel index (nx, ny) of the topmost - to + crossing along z, NaN if none."""
    return column_crossings_weights(d, w, min_weight)[0]


@njit(cache=True, nogil=True)
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


@njit(cache=True, nogil=True)
def window_reference_heights(heights_mm, cell_mm, i0, j0, i1, j1, voxel_mm):
    """Reference heights [mm] (ny, nx) at the voxel column centres ``i0:i1, j0:j1``: bilinear
    in the cell-centred grid ``heights_mm`` (:func:`dm2.reference.height_map.bilinear_at`)."""
    out = np.empty((j1 - j0, i1 - i0))
    for jj in range(j1 - j0):
        y = (j0 + jj + 0.5) * voxel_mm
        for ii in range(i1 - i0):
            out[jj, ii] = bilinear_at(heights_mm, cell_mm, (i0 + ii + 0.5) * voxel_mm, y)
    return out


@njit(cache=True, nogil=True)
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
    """(h, w) bool: ``hit`` dilated by the disk ``link`` (odd square of bools, each row one
    run), clipped. Each row's runs of hits are spread at once: a run ``[x0, x1]`` covers
    ``[x0 - s, x1 + s]`` on the row ``a`` away, ``s`` the disk's half width there."""
    h, w = hit.shape
    r = link.shape[0] // 2
    half = np.full(2 * r + 1, -1, np.int64)  # -1: the disk has no column on that row
    for a in range(2 * r + 1):
        for b in range(2 * r + 1):
            if link[a, b]:
                half[a] = max(half[a], abs(b - r))
    dil = np.zeros((h, w), np.bool_)
    for y in range(h):
        x = 0
        while x < w:
            if not hit[y, x]:
                x += 1
                continue
            x0 = x
            while x < w and hit[y, x]:
                x += 1
            x1 = x - 1
            for a in range(-r, r + 1):
                yy = y + a
                s = half[a + r]
                if s < 0 or not 0 <= yy < h:
                    continue
                for xx in range(max(x0 - s, 0), min(x1 + s, w - 1) + 1):
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
