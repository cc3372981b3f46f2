"""Planning of the two-thread TSDF update (:mod:`dm2.tsdf_split`): rays and block allocation.

1. :func:`plan_rays` (``nogil``, each thread a half of the points): registers the points
   (eq 1), decides each point's active region, stores every ray's origin, unit direction and
   range, deals the ray to the threads' block columns and lists, in the order the serial kernel
   first reaches them, the blocks its rays reach that are not allocated. The hash table is only
   read; a ray whose block box lies inside one of the last two boxes known to be allocated (or
   listed) needs no lookup, one whose box is not complete is walked with the update's DDA.
2. :func:`alloc_listed` and :func:`alloc_rays` (serial): allocate the listed blocks, thread 0's
   list before thread 1's, so block slots, keys and the hash match the serial kernel (a block
   missing before the batch is first reached by a listed ray). Should a list fill up, the rays
   from there on are walked in stream order instead.

``ray_f (n, 7)`` float64 holds ``ox, oy, oz, dx, dy, dz, r`` [mm]; ``ray_flags (n,)`` uint8 holds
bit 0/1: thread 0/1 must walk the ray, bit 2: the point is active, bit 3: the ray must be walked
to allocate (0: the ray is not fused).
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
    hash_find,
    hash_get_or_insert,
    pack_key,
)
from dm2.tsdf_point_rays import NO_POSE, point_ray, profile_pose

ACTIVE_FLAG = 4
NEW_BLOCK_FLAG = 8
RECENT = 1024  # entries of the cache of block keys a planning thread listed lately


@njit(cache=True, inline="always")
def _voxel_box(ox, oy, oz, dx, dy, dz, r, truncation_mm, inv_vox):
    """Voxel box ``vx0, vy0, vz0, vx1, vy1, vz1`` of a ray's band, one voxel of margin for
    rounding."""
    t0, t1 = r - truncation_mm, r + truncation_mm
    ax0, ax1 = (ox + dx * t0) * inv_vox, (ox + dx * t1) * inv_vox
    ay0, ay1 = (oy + dy * t0) * inv_vox, (oy + dy * t1) * inv_vox
    az0, az1 = (oz + dz * t0) * inv_vox, (oz + dz * t1) * inv_vox
    return int(np.floor(min(ax0, ax1))) - 1, int(np.floor(min(ay0, ay1))) - 1, \
        int(np.floor(min(az0, az1))) - 1, int(np.floor(max(ax0, ax1))) + 1, \
        int(np.floor(max(ay0, ay1))) + 1, int(np.floor(max(az0, az1))) + 1


@njit(cache=True, inline="always")
def _all_allocated(bx0, by0, bz0, bx1, by1, bz1, table_keys, table_slots, recent):
    """Whether every block of the box is allocated or in ``recent`` (listed to be)."""
    for bx in range(bx0, bx1 + 1):
        for by in range(by0, by1 + 1):
            for bz in range(bz0, bz1 + 1):
                key = pack_key(bx, by, bz)
                if recent[_hash(key, RECENT - 1)] != key and \
                        hash_find(table_keys, table_slots, key) < 0:
                    return False
    return True


@njit(cache=True, inline="always")
def _list_missing_blocks(ox, oy, oz, dx, dy, dz, r, truncation_mm, inv_vox, table_keys,
                         table_slots, new_keys, new_state, recent):
    """Walk the ray with the update's DDA and append the keys of the blocks it reaches that are
    neither allocated nor in ``recent`` (a direct-mapped cache of the keys listed so far) to
    ``new_keys`` (``new_state[0]`` entries so far). Returns -1 when the ray reaches no such
    block, 1 when it listed them all and 0 when the list is full."""
    vx, vy, vz, span, stx, sty, stz, tdx, tdy, tdz, tmx, tmy, tmz = dda_start(
        ox, oy, oz, dx, dy, dz, r, truncation_mm, inv_vox)
    last_bx, last_by, last_bz = 1 << 40, 0, 0
    found = -1
    t = 0.0
    while t <= span:
        bx, by, bz = vx >> BLOCK_SHIFT, vy >> BLOCK_SHIFT, vz >> BLOCK_SHIFT
        if bx != last_bx or by != last_by or bz != last_bz:
            key = pack_key(bx, by, bz)
            h = _hash(key, RECENT - 1)
            if recent[h] != key and hash_find(table_keys, table_slots, key) < 0:
                m = new_state[0]
                if m == new_keys.shape[0]:
                    return 0
                new_keys[m] = key
                new_state[0] = m + 1
                recent[h] = key
                found = 1
            last_bx, last_by, last_bz = bx, by, bz
        t, vx, vy, vz, tmx, tmy, tmz = dda_step(vx, vy, vz, stx, sty, stz, tdx, tdy, tdz,
                                                tmx, tmy, tmz)
    return found


@njit(cache=True, nogil=True)
def plan_rays(register, origins_O, points_O, active, xz_S, offsets, T_O_S, spot_O, axis_O,
              active_r2_mm2, bounds_lo, bounds_hi, use_bounds, i0, i1, voxel_mm, truncation_mm,
              col_shift, table_keys, table_slots, counts, ray_f, ray_flags, new_keys, new_state):
    """Rays of points ``i0:i1`` (arguments as in :func:`dm2.tsdf_kernels._fuse`): ``ray_f``,
    ``ray_flags`` and ``counts`` (skipped, fused) as the serial kernel counts them. Only reads
    the hash table, so two threads may plan disjoint ranges at once.

    The blocks the rays reach that are not allocated are listed in ``new_keys`` in the order
    the serial kernel first reaches them (``new_state[0]`` keys). Should the list fill up at
    ray ``j``, ``new_state[1] = j`` and the rays from ``j`` on that reach missing blocks are
    only marked with ``NEW_BLOCK_FLAG`` (else ``new_state[1] = i1``)."""
    inv_vox = 1.0 / voxel_mm
    cs = BLOCK_SHIFT + col_shift
    # a box of blocks known to be allocated: rays inside it need no lookup
    kx0, ky0, kz0, kx1, ky1, kz1 = 1, 1, 1, 0, 0, 0
    jx0, jy0, jz0, jx1, jy1, jz1 = 1, 1, 1, 0, 0, 0  # the box known before it
    new_state[0] = 0
    new_state[1] = i1
    listing = True
    recent = np.full(RECENT, EMPTY, dtype=np.int64)
    pose = NO_POSE
    for k in range(offsets.shape[0] - 1):
        if offsets[k + 1] <= i0 or offsets[k] >= i1:
            continue
        if register:
            pose = profile_pose(T_O_S, spot_O, axis_O, k)
        for i in range(max(offsets[k], i0), min(offsets[k + 1], i1)):
            ray_flags[i] = 0
            ok, ox, oy, oz, dx, dy, dz, r, act = point_ray(
                register, i, pose, xz_S, origins_O, points_O, active, active_r2_mm2, bounds_lo,
                bounds_hi, use_bounds, truncation_mm, counts)
            if not ok:
                continue
            ray_f[i, 0], ray_f[i, 1], ray_f[i, 2] = ox, oy, oz
            ray_f[i, 3], ray_f[i, 4], ray_f[i, 5], ray_f[i, 6] = dx, dy, dz, r
            vx0, vy0, vz0, vx1, vy1, vz1 = _voxel_box(ox, oy, oz, dx, dy, dz, r,
                                                      truncation_mm, inv_vox)
            cx0, cx1, cy0, cy1 = vx0 >> cs, vx1 >> cs, vy0 >> cs, vy1 >> cs
            flags = ACTIVE_FLAG if act else 0
            if cx0 == cx1 and cy0 == cy1:
                flags |= 1 << ((cx0 + cy0) & 1)
            else:
                flags |= 3
            bx0, by0, bz0 = vx0 >> BLOCK_SHIFT, vy0 >> BLOCK_SHIFT, vz0 >> BLOCK_SHIFT
            bx1, by1, bz1 = vx1 >> BLOCK_SHIFT, vy1 >> BLOCK_SHIFT, vz1 >> BLOCK_SHIFT
            if not (kx0 <= bx0 and bx1 <= kx1 and ky0 <= by0 and by1 <= ky1 and
                    kz0 <= bz0 and bz1 <= kz1) and \
                    not (jx0 <= bx0 and bx1 <= jx1 and jy0 <= by0 and by1 <= jy1 and
                         jz0 <= bz0 and bz1 <= jz1):
                if _all_allocated(bx0, by0, bz0, bx1, by1, bz1, table_keys, table_slots, recent):
                    jx0, jy0, jz0, jx1, jy1, jz1 = kx0, ky0, kz0, kx1, ky1, kz1
                    kx0, ky0, kz0, kx1, ky1, kz1 = bx0, by0, bz0, bx1, by1, bz1
                elif listing:
                    listed = _list_missing_blocks(ox, oy, oz, dx, dy, dz, r, truncation_mm,
                                                  inv_vox, table_keys, table_slots, new_keys,
                                                  new_state, recent)
                    if listed == 0:  # list full: this ray and later ones are walked serially
                        listing = False
                        new_state[1] = i
                        flags |= NEW_BLOCK_FLAG
                else:
                    flags |= NEW_BLOCK_FLAG
            ray_flags[i] = flags


@njit(cache=True)
def alloc_listed(new_keys, n_keys, start, table_keys, table_slots, block_keys, state):
    """Serial: allocate the listed block keys from entry ``start`` in order (keys already
    allocated are skipped). Returns the first entry not handled because the block arrays or the
    hash table need to grow (``n_keys`` when done)."""
    capacity = block_keys.shape[0]
    table_limit = table_keys.shape[0] // 2
    for j in range(start, n_keys):
        if state[0] + MAX_NEW_BLOCKS_PER_RAY > capacity or \
                state[0] + MAX_NEW_BLOCKS_PER_RAY > table_limit:
            return j
        hash_get_or_insert(new_keys[j], table_keys, table_slots, block_keys, state)
    return n_keys


@njit(cache=True)
def alloc_rays(ray_f, ray_flags, start, stop, voxel_mm, truncation_mm, table_keys,
               table_slots, block_keys, state):
    """Serial: allocate the blocks of the rays ``start:stop`` marked ``NEW_BLOCK_FLAG``,
    walking them in order with the update's DDA. Returns the index of the first ray not handled
    because the block arrays or the hash table need to grow (``stop`` when done)."""
    capacity = block_keys.shape[0]
    table_limit = table_keys.shape[0] // 2
    inv_vox = 1.0 / voxel_mm
    for i in range(start, stop):
        if not ray_flags[i] & NEW_BLOCK_FLAG:
            continue
        if state[0] + MAX_NEW_BLOCKS_PER_RAY > capacity or \
                state[0] + MAX_NEW_BLOCKS_PER_RAY > table_limit:
            return i
        ox, oy, oz = ray_f[i, 0], ray_f[i, 1], ray_f[i, 2]
        dx, dy, dz, r = ray_f[i, 3], ray_f[i, 4], ray_f[i, 5], ray_f[i, 6]
        vx, vy, vz, span, stx, sty, stz, tdx, tdy, tdz, tmx, tmy, tmz = dda_start(
            ox, oy, oz, dx, dy, dz, r, truncation_mm, inv_vox)
        last_bx, last_by, last_bz = 1 << 40, 0, 0
        t = 0.0
        while t <= span:
            bx, by, bz = vx >> BLOCK_SHIFT, vy >> BLOCK_SHIFT, vz >> BLOCK_SHIFT
            if bx != last_bx or by != last_by or bz != last_bz:
                hash_get_or_insert(pack_key(bx, by, bz), table_keys, table_slots, block_keys,
                                   state)
                last_bx, last_by, last_bz = bx, by, bz
            t, vx, vy, vz, tmx, tmy, tmz = dda_step(vx, vy, vz, stx, sty, stz, tdx, tdy,
                                                    tdz, tmx, tmy, tmz)
    return stop
