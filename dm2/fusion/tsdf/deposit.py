"""Deposition makes earlier observations stale: the weights around the spray spot are capped.

Cold spray only adds material. Where the spray spot passes, the surface the profilers saw a
moment ago is buried under the new deposit, yet a TSDF that keeps averaging keeps that old
surface in its mean: with the leading profiler seeing each point before the nozzle passes and
the trailing ones after, the fused top settled between the two, 0.10-0.14 mm (median) below
the true top of the twin's parts at about 0.8 mm per pass.

So before each profile is fused, every stored voxel within ``radius_mm`` of the spray axis at
its stamp (and within ``half_length_mm`` of the spot along it) keeps at most ``weight_cap`` of
weight: what was seen
there before now counts as that many observations, and the first profiles after the pass
decide the surface. A place no profiler sees again keeps its old surface, with the low weight
that makes its uncertainty large (dm2.defects.uncertainty). The signed distances are not
touched, so a cap of at least the extraction's ``min_weight`` changes no mesh by itself.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from dm2.fusion.tsdf.kernels import BLOCK, BLOCK_SHIFT, fuse_profiles, hash_find, pack_key, voxel_at


@njit(cache=True, inline="always")
def cap_box(voxel_mm, spot_O, axis_O, radius_mm, half_length_mm):
    """The voxel index box ``(lo (3,), hi (3,))`` int64 (inclusive) that holds every voxel centre
    of the cylinder of :func:`cap_near_axis`: along each axis, its own extent and its end discs'
    (plus 1 nm against rounding)."""
    lo = np.empty(3, np.int64)
    hi = np.empty(3, np.int64)
    for c in range(3):
        a = abs(axis_O[c])
        ext = a * half_length_mm + radius_mm * math.sqrt(max(1.0 - a * a, 0.0)) + 1e-6
        lo[c] = int(math.floor((spot_O[c] - ext) / voxel_mm))
        hi[c] = int(math.floor((spot_O[c] + ext) / voxel_mm))
    return lo, hi


@njit(cache=True, inline="always")
def cap_block(voxels, slot, bx, by, bz, lo, hi, voxel_mm, spot_O, axis_O, radius_mm,
              half_length_mm, weight_cap):
    """:func:`cap_near_axis` within block ``(bx, by, bz)`` stored in row ``slot`` of ``voxels``
    (``lo, hi``: :func:`cap_box`); returns the number of voxels capped."""
    r2 = radius_mm * radius_mm
    n = 0
    x0, y0, z0 = bx << BLOCK_SHIFT, by << BLOCK_SHIFT, bz << BLOCK_SHIFT
    for iz in range(max(lo[2] - z0, 0), min(hi[2] - z0, BLOCK - 1) + 1):
        for iy in range(max(lo[1] - y0, 0), min(hi[1] - y0, BLOCK - 1) + 1):
            for ix in range(max(lo[0] - x0, 0), min(hi[0] - x0, BLOCK - 1) + 1):
                li = ix + BLOCK * (iy + BLOCK * iz)
                if voxels[slot, li, 1] <= weight_cap:
                    continue
                x = (x0 + ix + 0.5) * voxel_mm - spot_O[0]
                y = (y0 + iy + 0.5) * voxel_mm - spot_O[1]
                z = (z0 + iz + 0.5) * voxel_mm - spot_O[2]
                along = x * axis_O[0] + y * axis_O[1] + z * axis_O[2]
                if abs(along) > half_length_mm or x * x + y * y + z * z - along * along > r2:
                    continue
                voxels[slot, li, 1] = weight_cap
                n += 1
    return n


@njit(cache=True, error_model="numpy", nogil=True)
def cap_near_axis(table_keys, table_slots, voxels, voxel_mm, spot_O, axis_O, radius_mm,
                  half_length_mm, weight_cap):
    """Cap at ``weight_cap`` the weight of every stored voxel whose centre lies within
    ``radius_mm`` of the line through ``spot_O (3,)`` [mm] along the unit ``axis_O (3,)`` and
    within ``half_length_mm`` of ``spot_O`` along it; returns the number of voxels capped."""
    lo, hi = cap_box(voxel_mm, spot_O, axis_O, radius_mm, half_length_mm)
    n = 0
    for bx in range(lo[0] >> BLOCK_SHIFT, (hi[0] >> BLOCK_SHIFT) + 1):
        for by in range(lo[1] >> BLOCK_SHIFT, (hi[1] >> BLOCK_SHIFT) + 1):
            for bz in range(lo[2] >> BLOCK_SHIFT, (hi[2] >> BLOCK_SHIFT) + 1):
                slot = hash_find(table_keys, table_slots, pack_key(bx, by, bz))
                if slot >= 0:
                    n += cap_block(voxels, slot, bx, by, bz, lo, hi, voxel_mm, spot_O, axis_O,
                                   radius_mm, half_length_mm, weight_cap)
    return n


@njit(cache=True, error_model="numpy", nogil=True)
def fuse_profiles_capped(xz_S, offsets, T_O_S, spot_O, axis_O, count, voxel_mm,
                         truncation_mm, active_weight_cap, max_weight, active_r2_mm2, bounds_lo,
                         bounds_hi, use_bounds, start, table_keys, table_slots, block_keys,
                         voxels, touched, state, counts, radius_mm, half_length_mm, weight_cap):
    """:func:`~dm2.fusion.tsdf.kernels.fuse_profiles` one profile at a time, each after
    :func:`cap_near_axis` around its own spray axis, in one call (the arguments are theirs).
    Returns the index of the first point not handled because the field must grow; a call
    resumed there caps again only profiles with no point fused yet, which finds nothing left
    to cap (no profile has been fused since)."""
    for c in range(offsets.shape[0] - 1):
        a, b = offsets[c], offsets[c + 1]
        if a < start:
            if b <= start:
                continue
            at = start - a
        else:
            cap_near_axis(table_keys, table_slots, voxels, voxel_mm, spot_O[c], axis_O[c],
                          radius_mm, half_length_mm, weight_cap)
            at = 0
        done = fuse_profiles(xz_S[a:b], offsets[c:c + 2] - a, T_O_S[c:c + 1], spot_O[c:c + 1],
                             axis_O[c:c + 1], count[a:b], voxel_mm, truncation_mm,
                             active_weight_cap, max_weight, active_r2_mm2, bounds_lo, bounds_hi,
                             use_bounds, at, table_keys, table_slots, block_keys, voxels, touched,
                             state, counts)
        if done < b - a:
            return a + done
    return xz_S.shape[0]


@njit(cache=True, error_model="numpy", nogil=True)
def cap_columns(table_keys, table_slots, voxels, voxel_mm, x_mm, y_mm, z_lo_mm, z_hi_mm,
                weight_cap):
    """Cap at ``weight_cap`` the weight of the stored voxels of the columns holding the points
    ``(x_mm[k], y_mm[k])`` between the heights ``z_lo_mm[k]`` and ``z_hi_mm[k]`` [mm] (a voxel
    whose centre's column and height fall there); returns the number of voxels capped."""
    n = 0
    for k in range(x_mm.shape[0]):
        ix = int(math.floor(x_mm[k] / voxel_mm))
        iy = int(math.floor(y_mm[k] / voxel_mm))
        iz0 = int(math.floor(z_lo_mm[k] / voxel_mm))
        iz1 = int(math.floor(z_hi_mm[k] / voxel_mm))
        for iz in range(iz0, iz1 + 1):
            slot, li = voxel_at(table_keys, table_slots, ix, iy, iz)
            if slot < 0:
                continue
            if voxels[slot, li, 1] > weight_cap:
                voxels[slot, li, 1] = weight_cap
                n += 1
    return n
