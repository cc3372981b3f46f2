"""Kernels of the two-thread TSDF fusion (:mod:`dm2.fusion.tsdf.threads`): block columns owned by
threads.

The voxels are dealt to the two threads by a checkerboard of block columns in ``x, y``
(``2**col_shift`` blocks wide). :func:`fuse_owned` (``nogil``, one call per thread) walks every
ray of the batch that reaches its thread's columns, with the serial kernel's DDA and arithmetic,
and updates only that thread's voxels. So every voxel is updated by exactly one thread, in ray
order, as the serial kernel (:func:`dm2.fusion.tsdf.kernels._fuse`) updates it: the fused field is
the
serial one bit for bit, whatever the thread timing.

The field's block table is only read while the threads run. A block a thread needs that is not
allocated yet goes into that thread's own staging area (keys and a small hash table) and its
voxels into rows of the field's voxel array reserved for that thread beyond the allocated
blocks; :func:`commit_staged` then allocates the staged blocks in the field, thread 0's before
thread 1's, each in the order its thread first reached them, moving their voxels down. Block
slots are therefore deterministic, though not in the serial kernel's order.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from dm2.fusion.tsdf.block_hash import (
    BLOCK_SHIFT,
    MAX_NEW_BLOCKS_PER_RAY,
    hash_get_or_insert,
    pack_key,
)
from dm2.fusion.tsdf.carve import CARVE_RUN_VOXELS, CARVE_TRUNCATIONS, walk_columns
from dm2.fusion.tsdf.deposit import cap_block, cap_box
from dm2.fusion.tsdf.point_rays import (
    NO_POSE,
    behind_scale,
    point_ray,
    profile_pose,
    ray_behind_scale,
)
from dm2.fusion.tsdf.ray_fuse import found_slot, fuse_ray, owner


@njit(cache=True, inline="always")
def _cap_owned(tid, col_shift, spot_O, axis_O, voxel_mm, deposit, table, voxels, base, staging):
    """Thread ``tid``'s part of :func:`dm2.fusion.tsdf.deposit.cap_near_axis` around ``spot_O,
    axis_O (3,)``: the blocks in its own columns, allocated or staged (``deposit``: radius,
    half length and cap as in :func:`fuse_owned`)."""
    radius_mm, half_length_mm, weight_cap = deposit
    lo, hi = cap_box(voxel_mm, spot_O, axis_O, radius_mm, half_length_mm)
    for bx in range(lo[0] >> BLOCK_SHIFT, (hi[0] >> BLOCK_SHIFT) + 1):
        for by in range(lo[1] >> BLOCK_SHIFT, (hi[1] >> BLOCK_SHIFT) + 1):
            if owner(bx, by, col_shift) != tid:
                continue
            for bz in range(lo[2] >> BLOCK_SHIFT, (hi[2] >> BLOCK_SHIFT) + 1):
                slot = found_slot(pack_key(bx, by, bz), table.keys, table.slots, base, staging)
                if slot >= 0:
                    cap_block(voxels, slot, bx, by, bz, lo, hi, voxel_mm, spot_O, axis_O,
                              radius_mm, half_length_mm, weight_cap)


@njit(cache=True, nogil=True, error_model="numpy")
def fuse_owned(tid, col_shift, start, register, use_bounds, batch, params, deposit, table,
               voxels, touched, counts, base, staging):
    """Thread ``tid`` (0 or 1): fuse its own voxels of the points of ``batch`` from ``start`` on
    (``batch``: a :class:`~dm2.fusion.tsdf.bundles.Batch`, ``params``: the
    :class:`~dm2.fusion.tsdf.bundles.FusionParams`, ``table``: the field's
    :class:`~dm2.fusion.tsdf.bundles.BlockHash`, ``voxels``, ``touched`` and the flags as in
    :func:`dm2.fusion.tsdf.kernels.fuse_profiles`; ``counts`` as the serial kernel counts the
    points walked); ``col_shift``: the checkerboard's columns are ``2**col_shift`` blocks wide;
    ``deposit``: ``(radius_mm, half_length_mm, weight_cap)`` of the cap around each profile's
    spray axis before its points (:mod:`dm2.fusion.tsdf.deposit`, each thread in its own
    columns, so the voxels see the serial ``fuse_profiles_capped``'s order), ``weight_cap <= 0``
    for none (rays are never capped).
    Bundled arguments: called twice per batch of thousands of points, whose typing by numba
    (a few microseconds) does not count.
    Blocks the field lacks are staged in ``staging`` (the thread's
    :class:`~dm2.fusion.tsdf.bundles.Staging`), their voxels in rows
    ``base:base + len(staging.keys)`` of ``voxels`` (zero). Returns the index of the first point
    not handled because the staging area is full (``len(xz_S)`` when done)."""
    if not register:  # literal flags: each variant is compiled without the other's tests
        return _owned(tid, col_shift, start, False, False, batch, params, deposit, table,
                      voxels, touched, counts, base, staging)
    if use_bounds:
        return _owned(tid, col_shift, start, True, True, batch, params, deposit, table, voxels,
                      touched, counts, base, staging)
    return _owned(tid, col_shift, start, True, False, batch, params, deposit, table, voxels,
                  touched, counts, base, staging)


@njit(cache=True, inline="always")
def _owned(tid, col_shift, start, register, use_bounds, batch, params, deposit, table, voxels,
           touched, counts, base, staging):
    """The loop of :func:`fuse_owned`, inlined with ``register`` and ``use_bounds`` as
    constants."""
    # the bundles' fields, read once here: a field read in a loop would be reference-counted
    origins_O, points_O, active, xz_S, offsets, T_O_S, spot_O, axis_O, count = batch
    voxel_mm, truncation_mm, active_weight_cap, max_weight, active_r2_mm2, bounds_lo, \
        bounds_hi = params
    table_keys, table_slots = table.keys, table.slots
    st_state = staging.state
    inv_vox = 1.0 / voxel_mm
    inv_trunc = 1.0 / truncation_mm
    carve_mm = CARVE_TRUNCATIONS * truncation_mm
    carve_vox = carve_mm * inv_vox
    consts = (truncation_mm, voxel_mm, inv_vox, inv_trunc, carve_vox, active_weight_cap,
              max_weight)
    cs = BLOCK_SHIFT + col_shift
    run = np.empty((CARVE_RUN_VOXELS, 2), dtype=np.int64)
    st_capacity = staging.keys.shape[0]
    pose = NO_POSE
    ra = rb = (1 << 40, 0, 0, -1)  # the two blocks looked up last (bx, by, bz, slot)
    capped = register and deposit[2] > 0.0
    for k in range(offsets.shape[0] - 1):
        if offsets[k] < start and offsets[k + 1] <= start:  # done before start
            continue
        if register:
            pose = profile_pose(T_O_S, spot_O, axis_O, k)
        if capped and offsets[k] >= start:  # a profile resumed mid-way was capped before
            _cap_owned(tid, col_shift, spot_O[k], axis_O[k], voxel_mm, deposit, table, voxels,
                       base, staging)
        for i in range(max(offsets[k], start), offsets[k + 1]):
            if st_state[0] + MAX_NEW_BLOCKS_PER_RAY > st_capacity:
                return i
            ok, ox, oy, oz, dx, dy, dz, r, act = point_ray(
                register, i, pose, xz_S, origins_O, points_O, active, count, active_r2_mm2,
                bounds_lo, bounds_hi, use_bounds, truncation_mm, counts)
            if not ok:
                continue
            n_i = count[i]
            # the columns of the ray's walk (an active ray walks on beyond its band, carving)
            cx0, cx1, cy0, cy1 = walk_columns(ox, oy, dx, dy, r, truncation_mm,
                                              carve_mm if act else 0.0, inv_vox, cs)
            mine = cx0 == cx1 and cy0 == cy1
            if mine and owner(cx0, cy0, 0) != tid:
                continue  # the other thread's column
            behind = (behind_scale(xz_S, i, offsets[k], offsets[k + 1]) if register else
                      ray_behind_scale(origins_O, points_O, i, points_O.shape[0], r))
            ra, rb = fuse_ray(True, tid, mine, cs, ox, oy, oz, dx, dy, dz, r, act, behind, n_i,
                              consts, table_keys, table_slots, table_keys, voxels, touched,
                              st_state, base, base, staging, run, ra, rb)
    return offsets[offsets.shape[0] - 1]


@njit(cache=True)
def commit_staged(staging, base, table, block_keys, voxels, touched, state):
    """Serial: give a thread's staged blocks (``staging``, staged in rows from ``base`` on) the
    next field slots in staging order (their voxels move down from the thread's reserved rows,
    which are zeroed again), mark them touched, and empty the staging area. ``table``: the
    field's :class:`~dm2.fusion.tsdf.bundles.BlockHash`; ``block_keys``, ``voxels``,
    ``touched``, ``state``: the field's, as in :func:`dm2.fusion.tsdf.kernels.fuse_profiles`.
    The caller makes room first."""
    st_keys, st_state = staging.keys, staging.state
    for j in range(st_state[0]):
        s = hash_get_or_insert(st_keys[j], table.keys, table.slots, block_keys, state)
        if s != base + j:
            voxels[s, :, :] = voxels[base + j, :, :]
            voxels[base + j, :, :] = 0.0
        touched[s] = True
        st_keys[j] = -1
    staging.table_keys[:] = -1
    st_state[0] = 0
