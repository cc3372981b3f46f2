"""Numba kernels of the sparse TSDF: block hash and ray integration (dense gathering:
:mod:`dm2.fusion.tsdf.dense`).

Storage layout (see :mod:`dm2.fusion.tsdf.field`): voxels live in blocks of ``BLOCK**3`` voxels,
found through the block hash (:mod:`dm2.fusion.tsdf.block_hash`, re-exported here) that maps a
block's key to a row ("slot") of the preallocated ``voxels`` array of shape ``(capacity, 512, 2)``
float32 that keeps each voxel's signed distance [mm] and weight side by side (one cache line per
update).

The integrator walks each sensor ray through the voxel grid with a 3-D DDA (Amanatides & Woo)
from ``truncation`` in front of the measured point to ``truncation`` behind it and updates every
voxel it crosses with the projective signed distance (eqs 2-3 of the paper; the walk and the
update: :mod:`dm2.fusion.tsdf.ray_walk`; one ray's band and carve, shared with the two-thread
kernel: :mod:`dm2.fusion.tsdf.ray_fuse`). ``fuse_profiles`` also registers the profiles (eq 1)
and decides each point's active region in the same pass.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from dm2.fusion.tsdf.block_hash import (  # noqa: F401  the block hash, re-exported
    BLOCK,
    BLOCK_SHIFT,
    BLOCK_VOXELS,
    EMPTY,
    MAX_NEW_BLOCKS_PER_RAY,
    hash_find,
    hash_get_or_insert,
    hash_insert,
    pack_key,
    rebuild_hash,
    recent_slot,
    unpack_keys,
    voxel_at,
)
from dm2.fusion.tsdf.bundles import BlockHash, FusionParams, Staging, profile_batch, ray_batch
from dm2.fusion.tsdf.carve import CARVE_RUN_VOXELS, CARVE_TRUNCATIONS, COL_SHIFT
from dm2.fusion.tsdf.point_rays import (
    NO_POSE,
    behind_scale,
    point_ray,
    profile_pose,
    ray_behind_scale,
)
from dm2.fusion.tsdf.ray_fuse import fuse_ray


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
    consts = (truncation_mm, voxel_mm, inv_vox, inv_trunc, carve_vox, active_weight_cap,
              max_weight)
    cs = BLOCK_SHIFT + COL_SHIFT
    run = np.empty((CARVE_RUN_VOXELS, 2), dtype=np.int64)
    no_staging = Staging(np.full(1, -1, dtype=np.int64), np.full(2, -1, dtype=np.int64),
                         np.full(2, -1, dtype=np.int32), np.zeros(1, dtype=np.int64))
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
            ra, rb = fuse_ray(False, 0, True, cs, ox, oy, oz, dx, dy, dz, r, act, behind,
                              n_i, consts, table_keys, table_slots, block_keys, voxels, touched,
                              state, capacity, 0, no_staging, run, ra, rb)
    return offsets[offsets.shape[0] - 1]
