"""The voxel update of the two-thread TSDF fusion (:mod:`dm2.tsdf_split`).

:func:`update_rays` (``nogil``, one call per thread) runs after the rays were planned and their
blocks allocated (:mod:`dm2.tsdf_plan_kernels`): the voxels are dealt to the threads by a
checkerboard of block columns in ``x, y`` (``2**col_shift`` blocks wide); each thread walks the
rays that reach its columns and updates only its own voxels. Every voxel is therefore updated by
exactly one thread, in ray order, with the serial kernel's arithmetic: the field, the weights and
the touched marks are bit-identical whatever the thread timing.
"""

from __future__ import annotations

from numba import njit

from dm2.tsdf_kernels import (
    BLOCK_SHIFT,
    dda_start,
    dda_step,
    hash_find,
    pack_key,
    recent_slot,
    update_voxel,
)
from dm2.tsdf_plan_kernels import ACTIVE_FLAG


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
    ra = rb = (1 << 40, 0, 0, -1)  # the two blocks looked up last (bx, by, bz, slot)
    for i in range(ray_flags.shape[0]):
        flags = ray_flags[i]
        if not flags & bit:
            continue
        act = (flags & ACTIVE_FLAG) != 0
        mine = (flags & 3) != 3  # the ray stays in this thread's columns
        ox, oy, oz = ray_f[i, 0], ray_f[i, 1], ray_f[i, 2]
        dx, dy, dz, r = ray_f[i, 3], ray_f[i, 4], ray_f[i, 5], ray_f[i, 6]
        vx, vy, vz, span, stx, sty, stz, tdx, tdy, tdz, tmx, tmy, tmz = dda_start(
            ox, oy, oz, dx, dy, dz, r, truncation_mm, inv_vox)
        last_bx, last_by, last_bz, slot = 1 << 40, 0, 0, -1
        t = 0.0
        while t <= span:
            if mine or ((vx >> cs) + (vy >> cs)) & 1 == tid:
                bx, by, bz = vx >> BLOCK_SHIFT, vy >> BLOCK_SHIFT, vz >> BLOCK_SHIFT
                if bx != last_bx or by != last_by or bz != last_bz:
                    slot = recent_slot(bx, by, bz, ra, rb)
                    if slot < 0:
                        slot = hash_find(table_keys, table_slots, pack_key(bx, by, bz))
                        if slot >= 0:
                            touched[slot] = True
                        ra, rb = (bx, by, bz, slot), ra
                    last_bx, last_by, last_bz = bx, by, bz
                if slot < 0:
                    missing += 1
                else:
                    update_voxel(voxels, slot, vx, vy, vz, ox, oy, oz, dx, dy, dz, r, voxel_mm,
                                 truncation_mm, act, active_weight_cap, max_weight)
            t, vx, vy, vz, tmx, tmy, tmz = dda_step(vx, vy, vz, stx, sty, stz, tdx, tdy, tdz,
                                                    tmx, tmy, tmz)
    return missing
