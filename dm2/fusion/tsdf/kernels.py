"""Numba kernels of the sparse TSDF: block hash and ray integration (dense gathering:
:mod:`dm2.fusion.tsdf.dense`).

Storage layout (see :mod:`dm2.fusion.tsdf.field`): voxels live in blocks of ``BLOCK**3`` voxels. A
block's
integer coordinates ``(bx, by, bz)`` are packed into one non-negative int64 key and found through
an open-addressing hash table (linear probing, ``EMPTY`` marks a free entry) that maps the key to
a row ("slot") of the preallocated ``voxels`` array of shape ``(capacity, 512, 2)`` float32 that
keeps each voxel's signed distance [mm] and weight side by side (one cache line per update).

The integrator walks each sensor ray through the voxel grid with a 3-D DDA (Amanatides & Woo)
from ``truncation`` in front of the measured point to ``truncation`` behind it and updates every
voxel it crosses with the projective signed distance (eqs 2-3 of the paper; the walk and the
update: :mod:`dm2.fusion.tsdf.ray_walk`). ``fuse_profiles`` also registers the profiles (eq 1)
and decides each point's active region in the same pass.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from dm2.fusion.tsdf.bundles import BlockHash, FusionParams, profile_batch, ray_batch
from dm2.fusion.tsdf.carve import (
    CARVE_RUN_VOXELS,
    CARVE_TRUNCATIONS,
    COL_SHIFT,
    carve_visit,
)
from dm2.fusion.tsdf.point_rays import (
    NO_POSE,
    behind_scale,
    point_ray,
    profile_pose,
    ray_behind_scale,
)
from dm2.fusion.tsdf.ray_walk import dda_start, dda_step, update_voxel

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


@njit(cache=True, inline="always")
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


@njit(cache=True, inline="always")
def voxel_at(table_keys, table_slots, ix, iy, iz):
    """``(slot, index within the block)`` of voxel ``(ix, iy, iz)``; slot -1: not stored."""
    slot = hash_find(table_keys, table_slots,
                     pack_key(ix >> BLOCK_SHIFT, iy >> BLOCK_SHIFT, iz >> BLOCK_SHIFT))
    li = (ix & (BLOCK - 1)) + BLOCK * ((iy & (BLOCK - 1)) + BLOCK * (iz & (BLOCK - 1)))
    return slot, li


@njit(cache=True)
def hash_insert(table_keys, table_slots, key, slot):
    mask = table_keys.shape[0] - 1
    h = _hash(key, mask)
    while table_keys[h] != EMPTY:
        h = (h + 1) & mask
    table_keys[h] = key
    table_slots[h] = slot


@njit(cache=True, nogil=True)
def rebuild_hash(block_keys, n_blocks, table_size):
    """A fresh hash table of ``table_size`` (power of two) entries for the first blocks."""
    table_keys = np.full(table_size, EMPTY, dtype=np.int64)
    table_slots = np.full(table_size, -1, dtype=np.int32)
    for s in range(n_blocks):
        hash_insert(table_keys, table_slots, block_keys[s], s)
    return table_keys, table_slots


@njit(cache=True, inline="always")
def hash_get_or_insert(key, table_keys, table_slots, block_keys, state):
    """Slot of ``key``; a new block (slot ``state[0]``, counted up) when it has none yet."""
    mask = table_keys.shape[0] - 1
    h = _hash(key, mask)
    while True:
        k = table_keys[h]
        if k == key:
            return table_slots[h]
        if k == EMPTY:
            s = state[0]
            state[0] += 1
            table_keys[h] = key
            table_slots[h] = s
            block_keys[s] = key
            return s
        h = (h + 1) & mask


@njit(cache=True, inline="always")
def _get_or_alloc(bx, by, bz, table_keys, table_slots, block_keys, touched, state):
    s = hash_get_or_insert(pack_key(bx, by, bz), table_keys, table_slots, block_keys, state)
    touched[s] = True
    return s


@njit(cache=True, inline="always")
def recent_slot(bx, by, bz, a, b):
    """Slot of block ``(bx, by, bz)`` when it is one of the two blocks looked up last (``a``,
    ``b``: ``(bx, by, bz, slot)``), else -1. Consecutive rays mostly cross the same two blocks,
    so most hash lookups are saved."""
    if bx == a[0] and by == a[1] and bz == a[2]:
        return a[3]
    if bx == b[0] and by == b[1] and bz == b[2]:
        return b[3]
    return -1


@njit(cache=True, error_model="numpy", nogil=True)
def integrate_rays(origins_O, points_O, active, voxel_mm, truncation_mm, active_weight_cap,
                   max_weight, table_keys, table_slots, block_keys, voxels, touched, state,
                   start):
    """Fuse the rays ``origins_O[i] -> points_O[i]`` (``(n, 3)`` float64 [mm, O], ``active
    (n,)`` bool) into the sparse TSDF, from index ``start``.

    ``voxel_mm, truncation_mm, active_weight_cap, max_weight``: as in
    :class:`~dm2.fusion.tsdf.bundles.FusionParams`; ``table_keys, table_slots``: the field's
    :class:`~dm2.fusion.tsdf.bundles.BlockHash`; ``block_keys (capacity,)`` int64, ``voxels
    (capacity, 512, 2)`` float32, ``touched (capacity,)`` bool the field's block rows;
    ``state[0]`` is the number of allocated blocks. Flat arguments, called from Python: the
    bundles are built here (see :mod:`dm2.fusion.tsdf.bundles`). Returns the index of the
    first ray that was not integrated because the block arrays or the hash table need to grow
    (``n`` when done).
    """
    no_bounds = np.zeros(0)
    params = FusionParams(voxel_mm, truncation_mm, active_weight_cap, max_weight, 0.0,
                          no_bounds, no_bounds)
    counts = np.zeros(2, dtype=np.int64)
    return _fuse(False, False, ray_batch(origins_O, points_O, active), params, start,
                 BlockHash(table_keys, table_slots), block_keys, voxels, touched, state, counts)


@njit(cache=True, error_model="numpy", nogil=True)
def fuse_profiles(xz_S, offsets, T_O_S, spot_O, axis_O, count, voxel_mm, truncation_mm,
                  active_weight_cap, max_weight, active_r2_mm2, bounds_lo, bounds_hi, use_bounds,
                  start, table_keys, table_slots, block_keys, voxels, touched, state, counts):
    """Register and fuse a batch of profiles (paper eq 1, then eqs 2-5), from point ``start``
    (the profiles' arrays as in :func:`~dm2.fusion.tsdf.bundles.profile_batch`, the constants
    as in :class:`~dm2.fusion.tsdf.bundles.FusionParams`, the field's arrays as in
    :func:`integrate_rays`; flat, built into the bundles here).

    Profile ``k`` owns points ``xz_S[offsets[k]:offsets[k + 1]]``, each standing for
    ``count[i]`` measured points (int64; the multiple of its weight, dm2.fusion.profile_merge;
    ones for single points); its point ``(x, z)`` lies at
    ``p = t + x * R[:, 0] + z * R[:, 2]`` in ``O`` with ``R, t`` of ``T_O_S[k]`` and its ray
    starts at ``t`` (the laser's emission point). A point is active when its distance from the
    nozzle axis through ``spot_O[k]`` along ``axis_O[k]`` is at most ``sqrt(active_r2_mm2)``.
    Points with ``z <= 0`` (behind the sensor) or, with ``use_bounds``, outside
    ``[bounds_lo, bounds_hi]`` are skipped and counted in ``counts[0]``; fused points are
    counted in ``counts[1]``. Returns the index of the first point not handled because the
    block arrays or the hash table need to grow (``len(xz_S)`` when done).
    """
    batch = profile_batch(xz_S, offsets, T_O_S, spot_O, axis_O, count)
    params = FusionParams(voxel_mm, truncation_mm, active_weight_cap, max_weight, active_r2_mm2,
                          bounds_lo, bounds_hi)
    table = BlockHash(table_keys, table_slots)
    if use_bounds:  # literal flags: each variant is compiled without the other's tests
        return _fuse(True, True, batch, params, start, table, block_keys, voxels, touched,
                     state, counts)
    return _fuse(True, False, batch, params, start, table, block_keys, voxels, touched, state,
                 counts)


@njit(cache=True, inline="always")
def _fuse(register, use_bounds, batch, params, start, table, block_keys, voxels, touched, state,
          counts):
    """The one integration loop behind :func:`integrate_rays` (``register=False``: rays given
    in ``O``) and :func:`fuse_profiles` (``register=True``: profiles registered here), inlined
    into each with ``register`` and ``use_bounds`` as constants.

    Signed distance ``d`` [mm] is positive in front of the measured point (free space towards
    the sensor) and negative behind it. Weights (eqs 4-5): 1 in front and ``1 - behind /
    truncation`` behind the point, in the active region (``w_A``) and elsewhere (``w_I``) alike
    (:mod:`dm2.fusion.tsdf.field`), none behind a profile point on an occluding edge
    (:func:`~dm2.fusion.tsdf.point_rays.behind_scale`). In the active region the stored weight
    is first capped at ``active_weight_cap``, and the walk goes on ``CARVE_TRUNCATIONS``
    truncations beyond the band through allocated blocks only, carving enclosed stale free space
    (:mod:`dm2.fusion.tsdf.carve`; a free run ends where the walk enters another two-thread
    column, as the two-thread kernel sees it).
    ``voxels[slot, li, 0]`` is the signed distance, ``voxels[slot, li, 1]`` the weight.
    """
    # the bundles' fields, read once here: a field read in a loop would be reference-counted
    origins_O, points_O, active, xz_S, offsets, T_O_S, spot_O, axis_O, count = batch
    voxel_mm, truncation_mm, active_weight_cap, max_weight, active_r2_mm2, bounds_lo, \
        bounds_hi = params
    table_keys, table_slots = table.keys, table.slots
    capacity = voxels.shape[0]
    table_limit = table_keys.shape[0] // 2
    inv_vox = 1.0 / voxel_mm
    inv_trunc = 1.0 / truncation_mm
    carve_vox = CARVE_TRUNCATIONS * truncation_mm * inv_vox
    cs = BLOCK_SHIFT + COL_SHIFT
    run = np.empty((CARVE_RUN_VOXELS, 2), dtype=np.int64)
    pose = NO_POSE
    ra = rb = (1 << 40, 0, 0, -1)  # the two blocks looked up last (bx, by, bz, slot)
    for k in range(offsets.shape[0] - 1):
        if offsets[k + 1] <= start:
            continue
        if register:
            pose = profile_pose(T_O_S, spot_O, axis_O, k)
        for i in range(max(offsets[k], start), offsets[k + 1]):
            if state[0] + MAX_NEW_BLOCKS_PER_RAY > capacity or \
                    state[0] + MAX_NEW_BLOCKS_PER_RAY > table_limit:
                return i
            ok, ox, oy, oz, dx, dy, dz, r, act = point_ray(
                register, i, pose, xz_S, origins_O, points_O, active, count, active_r2_mm2,
                bounds_lo, bounds_hi, use_bounds, truncation_mm, counts)
            if not ok:
                continue
            n_i = count[i]
            behind = (behind_scale(xz_S, i, offsets[k], offsets[k + 1]) if register else
                      ray_behind_scale(origins_O, points_O, i, points_O.shape[0], r))
            vx, vy, vz, span, tmx, tmy, tmz, d, steps = \
                dda_start(ox, oy, oz, dx, dy, dz, r, truncation_mm, voxel_mm, inv_vox)
            last_bx, last_by, last_bz, slot = 1 << 40, 0, 0, -1
            t = 0.0
            while t <= span:
                bx, by, bz = vx >> BLOCK_SHIFT, vy >> BLOCK_SHIFT, vz >> BLOCK_SHIFT
                if bx != last_bx or by != last_by or bz != last_bz:
                    slot = recent_slot(bx, by, bz, ra, rb)
                    if slot < 0:
                        slot = _get_or_alloc(bx, by, bz, table_keys, table_slots, block_keys,
                                             touched, state)
                        ra, rb = (bx, by, bz, slot), ra
                    last_bx, last_by, last_bz = bx, by, bz
                update_voxel(voxels, slot, vx, vy, vz, d, truncation_mm, inv_trunc, act,
                             active_weight_cap, max_weight, behind, n_i)
                t, vx, vy, vz, tmx, tmy, tmz, d = dda_step(vx, vy, vz, tmx, tmy, tmz, d, steps)
            if not act:
                continue
            # beyond the band: allocated blocks only; a free run ends at a column edge
            end = span + carve_vox
            n_run, run_cx, run_cy = 0, 1 << 40, 0
            while t <= end:
                if (vx >> cs) != run_cx or (vy >> cs) != run_cy:
                    n_run, run_cx, run_cy = 0, vx >> cs, vy >> cs
                bx, by, bz = vx >> BLOCK_SHIFT, vy >> BLOCK_SHIFT, vz >> BLOCK_SHIFT
                if bx != last_bx or by != last_by or bz != last_bz:
                    slot = recent_slot(bx, by, bz, ra, rb)
                    if slot < 0:
                        slot = hash_find(table_keys, table_slots, pack_key(bx, by, bz))
                        if slot >= 0:
                            ra, rb = (bx, by, bz, slot), ra
                    last_bx, last_by, last_bz = bx, by, bz
                n_run = carve_visit(voxels, slot, vx, vy, vz, truncation_mm, run, n_run,
                                    touched, capacity)
                t, vx, vy, vz, tmx, tmy, tmz, d = dda_step(vx, vy, vz, tmx, tmy, tmz, d, steps)
    return offsets[offsets.shape[0] - 1]
