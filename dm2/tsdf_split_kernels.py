"""Two-thread TSDF integration that gives the same bits as the serial kernel.

The serial pass of :mod:`dm2.tsdf_kernels` is split in two:

1. :func:`plan_rays` (serial): registers the points (eq 1), decides each point's active region,
   stores every ray's origin, unit direction and range, and allocates the blocks the rays will
   cross, in the serial kernel's order (so block slots, keys and the hash match it). A ray whose
   block box lies inside a box already known to be allocated needs no walk; others are walked
   with the same DDA as the update.
2. :func:`update_rays` (``nogil``, one call per thread): the voxels are dealt to the threads by a
   checkerboard of block columns in ``x, y`` (``2**col_shift`` blocks wide); each thread walks the
   rays that reach its columns and updates only its own voxels. Every voxel is therefore updated
   by exactly one thread, in ray order, with the serial kernel's arithmetic: the field, the
   weights and the touched marks are bit-identical whatever the thread timing.

``ray_f (n, 7)`` float64 holds ``ox, oy, oz, dx, dy, dz, r`` [mm]; ``ray_flags (n,)`` uint8 holds
bit 0/1: thread 0/1 must walk the ray, bit 2: the point is active (0: the ray is not fused).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from dm2.tsdf_kernels import (
    BLOCK_SHIFT,
    EMPTY,
    MAX_NEW_BLOCKS_PER_RAY,
    _hash,
    dda_start,
    dda_step,
    pack_key,
    update_voxel,
)

ACTIVE_FLAG = 4


@njit(cache=True, inline="always")
def _alloc(bx, by, bz, table_keys, table_slots, block_keys, state):
    key = pack_key(bx, by, bz)
    mask = table_keys.shape[0] - 1
    h = _hash(key, mask)
    while True:
        k = table_keys[h]
        if k == key:
            return
        if k == EMPTY:
            s = state[0]
            state[0] += 1
            table_keys[h] = key
            table_slots[h] = s
            block_keys[s] = key
            return
        h = (h + 1) & mask


@njit(cache=True, inline="always")
def _find(table_keys, table_slots, key):
    mask = table_keys.shape[0] - 1
    h = _hash(key, mask)
    while True:
        k = table_keys[h]
        if k == key:
            return table_slots[h]
        if k == EMPTY:
            return -1
        h = (h + 1) & mask


@njit(cache=True)
def plan_rays(register, origins_O, points_O, active, xz_S, offsets, T_O_S, spot_O, axis_O,
              active_r2_mm2, bounds_lo, bounds_hi, use_bounds, start, voxel_mm, truncation_mm,
              col_shift, table_keys, table_slots, block_keys, state, counts, ray_f, ray_flags):
    """Serial pass: rays and block allocation of points from ``start`` (arguments as in
    :func:`dm2.tsdf_kernels._fuse`). Returns the index of the first point not handled because
    the block arrays or the hash table need to grow (the number of points when done)."""
    capacity = block_keys.shape[0]
    table_limit = table_keys.shape[0] // 2
    inv_vox = 1.0 / voxel_mm
    cs = BLOCK_SHIFT + col_shift
    # a box of blocks known to be allocated: rays inside it need no walk
    kx0, ky0, kz0, kx1, ky1, kz1 = 1, 1, 1, 0, 0, 0
    r00 = r10 = r20 = r02 = r12 = r22 = ox = oy = oz = sx = sy = sz = ax = ay = az = 0.0
    for k in range(offsets.shape[0] - 1):
        if offsets[k + 1] <= start:
            continue
        if register:
            r00, r10, r20 = T_O_S[k, 0, 0], T_O_S[k, 1, 0], T_O_S[k, 2, 0]
            r02, r12, r22 = T_O_S[k, 0, 2], T_O_S[k, 1, 2], T_O_S[k, 2, 2]
            ox, oy, oz = T_O_S[k, 0, 3], T_O_S[k, 1, 3], T_O_S[k, 2, 3]
            sx, sy, sz = spot_O[k, 0], spot_O[k, 1], spot_O[k, 2]
            ax, ay, az = axis_O[k, 0], axis_O[k, 1], axis_O[k, 2]
        for i in range(max(offsets[k], start), offsets[k + 1]):
            if state[0] + MAX_NEW_BLOCKS_PER_RAY > capacity or \
                    state[0] + MAX_NEW_BLOCKS_PER_RAY > table_limit:
                return i
            ray_flags[i] = 0
            if register:
                x, z = xz_S[i, 0], xz_S[i, 1]
                if not z > 0.0:  # behind the sensor
                    counts[0] += 1
                    continue
                px = ox + r00 * x + r02 * z
                py = oy + r10 * x + r12 * z
                pz = oz + r20 * x + r22 * z
                if use_bounds and not (bounds_lo[0] <= px <= bounds_hi[0]
                                       and bounds_lo[1] <= py <= bounds_hi[1]
                                       and bounds_lo[2] <= pz <= bounds_hi[2]):
                    counts[0] += 1
                    continue
                qx, qy, qz = px - sx, py - sy, pz - sz
                along = qx * ax + qy * ay + qz * az
                act = (qx * qx + qy * qy + qz * qz) - along * along <= active_r2_mm2
            else:
                ox, oy, oz = origins_O[i, 0], origins_O[i, 1], origins_O[i, 2]
                px, py, pz = points_O[i, 0], points_O[i, 1], points_O[i, 2]
                act = active[i]
            counts[1] += 1
            dx, dy, dz = px - ox, py - oy, pz - oz
            r = np.sqrt(dx * dx + dy * dy + dz * dz)
            if r <= truncation_mm:
                continue
            dx /= r
            dy /= r
            dz /= r
            ray_f[i, 0], ray_f[i, 1], ray_f[i, 2] = ox, oy, oz
            ray_f[i, 3], ray_f[i, 4], ray_f[i, 5], ray_f[i, 6] = dx, dy, dz, r
            # voxel box of the band, one voxel of margin for rounding -> block box
            t0, t1 = r - truncation_mm, r + truncation_mm
            ax0, ax1 = (ox + dx * t0) * inv_vox, (ox + dx * t1) * inv_vox
            ay0, ay1 = (oy + dy * t0) * inv_vox, (oy + dy * t1) * inv_vox
            az0, az1 = (oz + dz * t0) * inv_vox, (oz + dz * t1) * inv_vox
            vx0 = int(np.floor(min(ax0, ax1))) - 1
            vy0 = int(np.floor(min(ay0, ay1))) - 1
            vz0 = int(np.floor(min(az0, az1))) - 1
            vx1 = int(np.floor(max(ax0, ax1))) + 1
            vy1 = int(np.floor(max(ay0, ay1))) + 1
            vz1 = int(np.floor(max(az0, az1))) + 1
            cx0, cx1, cy0, cy1 = vx0 >> cs, vx1 >> cs, vy0 >> cs, vy1 >> cs
            flags = ACTIVE_FLAG if act else 0
            if cx0 == cx1 and cy0 == cy1:
                flags |= 1 << ((cx0 + cy0) & 1)
            else:
                flags |= 3
            ray_flags[i] = flags
            bx0, by0, bz0 = vx0 >> BLOCK_SHIFT, vy0 >> BLOCK_SHIFT, vz0 >> BLOCK_SHIFT
            bx1, by1, bz1 = vx1 >> BLOCK_SHIFT, vy1 >> BLOCK_SHIFT, vz1 >> BLOCK_SHIFT
            if kx0 <= bx0 and bx1 <= kx1 and ky0 <= by0 and by1 <= ky1 and \
                    kz0 <= bz0 and bz1 <= kz1:
                continue
            complete = True
            for bx in range(bx0, bx1 + 1):
                for by in range(by0, by1 + 1):
                    for bz in range(bz0, bz1 + 1):
                        if complete and _find(table_keys, table_slots,
                                              pack_key(bx, by, bz)) < 0:
                            complete = False
            if complete:
                kx0, ky0, kz0, kx1, ky1, kz1 = bx0, by0, bz0, bx1, by1, bz1
                continue
            # walk the ray like the update does and allocate its blocks in order
            vx, vy, vz, span, stx, sty, stz, tdx, tdy, tdz, tmx, tmy, tmz = dda_start(
                ox, oy, oz, dx, dy, dz, r, truncation_mm, inv_vox)
            last_bx, last_by, last_bz = 1 << 40, 0, 0
            t = 0.0
            while t <= span:
                bx, by, bz = vx >> BLOCK_SHIFT, vy >> BLOCK_SHIFT, vz >> BLOCK_SHIFT
                if bx != last_bx or by != last_by or bz != last_bz:
                    _alloc(bx, by, bz, table_keys, table_slots, block_keys, state)
                    last_bx, last_by, last_bz = bx, by, bz
                t, vx, vy, vz, tmx, tmy, tmz = dda_step(vx, vy, vz, stx, sty, stz, tdx, tdy,
                                                        tdz, tmx, tmy, tmz)
    return offsets[offsets.shape[0] - 1]


@njit(cache=True, nogil=True)
def update_rays(tid, col_shift, ray_f, ray_flags, voxel_mm, truncation_mm, active_weight_cap,
                max_weight, table_keys, table_slots, voxels, touched):
    """Thread ``tid`` (0 or 1): update its own voxels along every planned ray that reaches its
    block columns (eqs 2-5 with the weight cap, the serial kernel's arithmetic). Returns the
    number of voxel visits whose block was missing (0 unless the plan was wrong)."""
    inv_vox = 1.0 / voxel_mm
    cs = BLOCK_SHIFT + col_shift
    bit = 1 << tid
    missing = 0
    for i in range(ray_flags.shape[0]):
        flags = ray_flags[i]
        if not flags & bit:
            continue
        act = (flags & ACTIVE_FLAG) != 0
        ox, oy, oz = ray_f[i, 0], ray_f[i, 1], ray_f[i, 2]
        dx, dy, dz, r = ray_f[i, 3], ray_f[i, 4], ray_f[i, 5], ray_f[i, 6]
        vx, vy, vz, span, stx, sty, stz, tdx, tdy, tdz, tmx, tmy, tmz = dda_start(
            ox, oy, oz, dx, dy, dz, r, truncation_mm, inv_vox)
        last_bx, last_by, last_bz, slot = 1 << 40, 0, 0, -1
        t = 0.0
        while t <= span:
            if ((vx >> cs) + (vy >> cs)) & 1 == tid:
                bx, by, bz = vx >> BLOCK_SHIFT, vy >> BLOCK_SHIFT, vz >> BLOCK_SHIFT
                if bx != last_bx or by != last_by or bz != last_bz:
                    slot = _find(table_keys, table_slots, pack_key(bx, by, bz))
                    if slot >= 0:
                        touched[slot] = True
                    last_bx, last_by, last_bz = bx, by, bz
                if slot < 0:
                    missing += 1
                else:
                    update_voxel(voxels, slot, vx, vy, vz, ox, oy, oz, dx, dy, dz, r, voxel_mm,
                                 truncation_mm, act, active_weight_cap, max_weight)
            t, vx, vy, vz, tmx, tmy, tmz = dda_step(vx, vy, vz, stx, sty, stz, tdx, tdy, tdz,
                                                    tmx, tmy, tmz)
    return missing
