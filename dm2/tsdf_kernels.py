"""Numba kernels of the sparse TSDF: block hash, ray integration and dense gathering.

Storage layout (see :mod:`dm2.tsdf`): voxels live in blocks of ``BLOCK**3`` voxels. A block's
integer coordinates ``(bx, by, bz)`` are packed into one non-negative int64 key and found through
an open-addressing hash table (linear probing, ``EMPTY`` marks a free entry) that maps the key to
a row ("slot") of the preallocated ``tsdf_mm`` / ``weight`` arrays of shape ``(capacity, 512)``.

The integrator walks each sensor ray through the voxel grid with a 3-D DDA (Amanatides & Woo)
from ``truncation`` in front of the measured point to ``truncation`` behind it and updates every
voxel it crosses with the projective signed distance (eqs 2-3 of the paper).
"""

from __future__ import annotations

import numpy as np
from numba import njit

BLOCK = 8  # voxels per block edge
BLOCK_SHIFT = 3
BLOCK_VOXELS = BLOCK**3
EMPTY = -1
_OFFSET = 1 << 20  # block coordinates in [-2**20, 2**20) pack into 21 bits each
_MASK21 = (1 << 21) - 1
# Worst case of new blocks one ray can need: rays span at most 2 * truncation, a few blocks.
MAX_NEW_BLOCKS_PER_RAY = 16


@njit(cache=True, inline="always")
def pack_key(bx, by, bz):
    return ((bx + _OFFSET) << 42) | ((by + _OFFSET) << 21) | (bz + _OFFSET)


@njit(cache=True)
def unpack_keys(keys):
    """Block coordinates ``(n, 3)`` int64 of packed keys ``(n,)``."""
    out = np.empty((keys.shape[0], 3), dtype=np.int64)
    for i in range(keys.shape[0]):
        k = keys[i]
        out[i, 0] = ((k >> 42) & _MASK21) - _OFFSET
        out[i, 1] = ((k >> 21) & _MASK21) - _OFFSET
        out[i, 2] = (k & _MASK21) - _OFFSET
    return out


@njit(cache=True, inline="always")
def _hash(key, mask):
    h = np.uint64(key) * np.uint64(0x9E3779B97F4A7C15)
    return np.int64(h >> np.uint64(40)) & mask


@njit(cache=True)
def hash_find(table_keys, table_slots, key):
    """Slot of ``key`` or -1."""
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
def hash_insert(table_keys, table_slots, key, slot):
    mask = table_keys.shape[0] - 1
    h = _hash(key, mask)
    while table_keys[h] != EMPTY:
        h = (h + 1) & mask
    table_keys[h] = key
    table_slots[h] = slot


@njit(cache=True)
def rebuild_hash(block_keys, n_blocks, table_size):
    """A fresh hash table of ``table_size`` (power of two) entries for the first blocks."""
    table_keys = np.full(table_size, EMPTY, dtype=np.int64)
    table_slots = np.full(table_size, -1, dtype=np.int32)
    for s in range(n_blocks):
        hash_insert(table_keys, table_slots, block_keys[s], s)
    return table_keys, table_slots


@njit(cache=True, inline="always")
def _get_or_alloc(bx, by, bz, table_keys, table_slots, block_keys, touched, state):
    key = pack_key(bx, by, bz)
    mask = table_keys.shape[0] - 1
    h = _hash(key, mask)
    while True:
        k = table_keys[h]
        if k == key:
            s = table_slots[h]
            touched[s] = True
            return s
        if k == EMPTY:
            s = state[0]
            state[0] += 1
            table_keys[h] = key
            table_slots[h] = s
            block_keys[s] = key
            touched[s] = True
            return s
        h = (h + 1) & mask


@njit(cache=True)
def integrate_rays(origins_O, points_O, active, voxel_mm, truncation_mm, active_weight_cap,
                   max_weight, table_keys, table_slots, block_keys, tsdf_mm, weight, touched,
                   state, start):
    """Fuse rays ``origins_O[i] -> points_O[i]`` into the sparse TSDF, from index ``start``.

    Signed distance ``d`` [mm] is positive in front of the measured point (free space towards
    the sensor) and negative behind it. Weights: ``w_A = 1`` over the whole band in the active
    region; ``w_I = 1`` in front and ``1 - behind / truncation`` behind the point elsewhere
    (eqs 4-5). In the active region the stored weight is first capped at ``active_weight_cap``.

    ``state[0]`` is the number of allocated blocks. Returns the index of the first ray that was
    not integrated because the block arrays or the hash table need to grow (``n`` when done).
    """
    n = points_O.shape[0]
    capacity = tsdf_mm.shape[0]
    table_limit = table_keys.shape[0] // 2
    inv_vox = 1.0 / voxel_mm
    for i in range(start, n):
        if state[0] + MAX_NEW_BLOCKS_PER_RAY > capacity or \
                state[0] + MAX_NEW_BLOCKS_PER_RAY > table_limit:
            return i
        ox, oy, oz = origins_O[i, 0], origins_O[i, 1], origins_O[i, 2]
        dx, dy, dz = points_O[i, 0] - ox, points_O[i, 1] - oy, points_O[i, 2] - oz
        r = np.sqrt(dx * dx + dy * dy + dz * dz)
        if r <= truncation_mm:
            continue
        dx /= r
        dy /= r
        dz /= r
        act = active[i]
        t0 = r - truncation_mm
        t1 = r + truncation_mm
        # DDA in voxel units from t0 to t1
        sx, sy, sz = (ox + dx * t0) * inv_vox, (oy + dy * t0) * inv_vox, (oz + dz * t0) * inv_vox
        vx, vy, vz = int(np.floor(sx)), int(np.floor(sy)), int(np.floor(sz))
        span = (t1 - t0) * inv_vox
        stx = 1 if dx > 0 else -1
        sty = 1 if dy > 0 else -1
        stz = 1 if dz > 0 else -1
        big = 1e30
        tdx = abs(1.0 / dx) if dx != 0 else big
        tdy = abs(1.0 / dy) if dy != 0 else big
        tdz = abs(1.0 / dz) if dz != 0 else big
        tmx = ((vx + 1 - sx) if dx > 0 else (sx - vx)) * tdx if dx != 0 else big
        tmy = ((vy + 1 - sy) if dy > 0 else (sy - vy)) * tdy if dy != 0 else big
        tmz = ((vz + 1 - sz) if dz > 0 else (sz - vz)) * tdz if dz != 0 else big
        last_bx, last_by, last_bz, slot = 1 << 40, 0, 0, -1
        t = 0.0
        while t <= span:
            bx, by, bz = vx >> BLOCK_SHIFT, vy >> BLOCK_SHIFT, vz >> BLOCK_SHIFT
            if bx != last_bx or by != last_by or bz != last_bz:
                slot = _get_or_alloc(bx, by, bz, table_keys, table_slots, block_keys, touched,
                                     state)
                last_bx, last_by, last_bz = bx, by, bz
            cx = (vx + 0.5) * voxel_mm - ox
            cy = (vy + 0.5) * voxel_mm - oy
            cz = (vz + 0.5) * voxel_mm - oz
            d = r - (cx * dx + cy * dy + cz * dz)
            if d > truncation_mm:
                d = truncation_mm
            elif d < -truncation_mm:
                d = -truncation_mm
            if act or d >= 0.0:
                w = 1.0
            else:
                w = 1.0 + d / truncation_mm
            if w > 0.0:
                li = (vx & 7) + 8 * ((vy & 7) + 8 * (vz & 7))
                w_prev = weight[slot, li]
                if act and w_prev > active_weight_cap:
                    w_prev = active_weight_cap
                w_new = w_prev + w
                tsdf_mm[slot, li] = (w_prev * tsdf_mm[slot, li] + w * d) / w_new
                weight[slot, li] = min(w_new, max_weight)
            # step to the next voxel
            if tmx < tmy:
                if tmx < tmz:
                    t = tmx
                    vx += stx
                    tmx += tdx
                else:
                    t = tmz
                    vz += stz
                    tmz += tdz
            else:
                if tmy < tmz:
                    t = tmy
                    vy += sty
                    tmy += tdy
                else:
                    t = tmz
                    vz += stz
                    tmz += tdz
    return n


@njit(cache=True)
def gather_dense(table_keys, table_slots, tsdf_mm, weight, origin_voxel, shape, fill_mm):
    """Dense ``tsdf (shape)`` and ``weight (shape)`` sub-volumes starting at voxel index
    ``origin_voxel (3,)``; voxels of unallocated blocks get ``fill_mm`` and weight 0."""
    nx, ny, nz = shape[0], shape[1], shape[2]
    out_d = np.full((nx, ny, nz), fill_mm, dtype=np.float32)
    out_w = np.zeros((nx, ny, nz), dtype=np.float32)
    ox, oy, oz = origin_voxel[0], origin_voxel[1], origin_voxel[2]
    # iterate block by block
    bx0, by0, bz0 = ox >> BLOCK_SHIFT, oy >> BLOCK_SHIFT, oz >> BLOCK_SHIFT
    bx1 = (ox + nx - 1) >> BLOCK_SHIFT
    by1 = (oy + ny - 1) >> BLOCK_SHIFT
    bz1 = (oz + nz - 1) >> BLOCK_SHIFT
    for bx in range(bx0, bx1 + 1):
        for by in range(by0, by1 + 1):
            for bz in range(bz0, bz1 + 1):
                s = hash_find(table_keys, table_slots, pack_key(bx, by, bz))
                if s < 0:
                    continue
                for lz in range(BLOCK):
                    gz = bz * BLOCK + lz - oz
                    if gz < 0 or gz >= nz:
                        continue
                    for ly in range(BLOCK):
                        gy = by * BLOCK + ly - oy
                        if gy < 0 or gy >= ny:
                            continue
                        for lx in range(BLOCK):
                            gx = bx * BLOCK + lx - ox
                            if gx < 0 or gx >= nx:
                                continue
                            li = lx + BLOCK * (ly + BLOCK * lz)
                            out_d[gx, gy, gz] = tsdf_mm[s, li]
                            out_w[gx, gy, gz] = weight[s, li]
    return out_d, out_w
