"""One ray fused into the sparse TSDF: the band walk and the carve beyond it, written once for the
serial kernel (:func:`dm2.fusion.tsdf.kernels._fuse`) and the two-thread one
(:func:`dm2.fusion.tsdf.owned_kernels.fuse_owned`).

:func:`fuse_ray` is inlined into both (``inline="always"``) with ``owned`` a literal: the serial
kernel (``owned=False``) updates every voxel the ray crosses and allocates the blocks it lacks in
the field; a thread of the two-thread kernel (``owned=True``) updates only the voxels in its own
block columns and stages the blocks the field lacks in its own staging area. Both run the same
DDA and the same update in the same order, so their fields are bit-identical.
"""

from __future__ import annotations

from numba import njit

from dm2.fusion.tsdf.block_hash import (
    BLOCK_SHIFT,
    hash_find,
    hash_get_or_insert,
    pack_key,
    recent_slot,
)
from dm2.fusion.tsdf.carve import carve_visit
from dm2.fusion.tsdf.ray_walk import dda_start, dda_step, update_voxel


@njit(cache=True, nogil=True)
def staged_slot(key, base, staging):
    """Field row of a block the field lacks: its row in the thread's reserved rows (staged
    now when new; ``staging``: the thread's :class:`~dm2.fusion.tsdf.bundles.Staging`). Not
    inlined: the fusion loop stays small, and this path is rare."""
    return base + hash_get_or_insert(key, staging.table_keys, staging.table_slots, staging.keys,
                                     staging.state)


@njit(cache=True, nogil=True)
def found_slot(key, table_keys, table_slots, base, staging):
    """Field row of an allocated (``table_keys, table_slots``: the field's hash) or staged
    block, -1 for neither (the carve beyond a ray's band allocates nothing)."""
    s = hash_find(table_keys, table_slots, key)
    if s >= 0:
        return s
    s = hash_find(staging.table_keys, staging.table_slots, key)
    return base + s if s >= 0 else -1


@njit(cache=True, inline="always")
def owner(x, y, shift):
    """The thread (0 or 1) that owns the column holding index ``(x, y)``: columns are
    ``2**shift`` indices wide, dealt as a checkerboard (voxel indices with ``BLOCK_SHIFT +
    col_shift``, block indices with ``col_shift``, column indices with 0)."""
    return ((x >> shift) + (y >> shift)) & 1


@njit(cache=True, inline="always")
def fuse_ray(owned, tid, mine, cs, ox, oy, oz, dx, dy, dz, r, act, behind, n_i, consts,
             table_keys, table_slots, block_keys, voxels, touched, state, limit, base, staging,
             run, ra, rb):
    """Fuse one ray (origin ``(ox, oy, oz)`` [mm, O], unit direction ``(dx, dy, dz)``, measured
    point at ``r`` [mm]; ``act``: in the active region; ``behind``: the weight's scale behind
    the point; ``n_i``: the points it stands for) and return the two blocks looked up last
    ``(ra, rb)`` for the next ray.

    ``consts`` = ``(truncation_mm, voxel_mm, inv_vox, inv_trunc, carve_vox, active_weight_cap,
    max_weight)``. ``cs``: the shift of a voxel index to its block column (``BLOCK_SHIFT`` plus
    the column width's). With ``owned`` only the voxels of thread ``tid``'s columns are touched
    (all of them when ``mine``: the whole walk lies in one column of its own), and blocks the
    field lacks are staged (``base``, ``staging``); otherwise they are allocated in the field
    (``block_keys``, ``state``). ``limit``: the rows below which a carve may write (the
    field's capacity, or a thread's ``base``). An active ray walks on beyond its band
    through allocated blocks only, carving enclosed stale free space
    (:mod:`dm2.fusion.tsdf.carve`); a free run ends where the walk enters another column.
    """
    truncation_mm, voxel_mm, inv_vox, inv_trunc, carve_vox, active_weight_cap, max_weight = \
        consts
    vx, vy, vz, span, tmx, tmy, tmz, d, steps = \
        dda_start(ox, oy, oz, dx, dy, dz, r, truncation_mm, voxel_mm, inv_vox)
    last_bx, last_by, last_bz, slot = 1 << 40, 0, 0, -1
    t = 0.0
    while t <= span:
        if not owned or mine or owner(vx, vy, cs) == tid:
            bx, by, bz = vx >> BLOCK_SHIFT, vy >> BLOCK_SHIFT, vz >> BLOCK_SHIFT
            if bx != last_bx or by != last_by or bz != last_bz:
                slot = recent_slot(bx, by, bz, ra, rb)
                if slot < 0:
                    key = pack_key(bx, by, bz)
                    if owned:
                        slot = hash_find(table_keys, table_slots, key)
                        if slot >= 0:
                            touched[slot] = True
                        else:
                            slot = staged_slot(key, base, staging)
                    else:
                        slot = hash_get_or_insert(key, table_keys, table_slots, block_keys,
                                                  state)
                        touched[slot] = True
                    ra, rb = (bx, by, bz, slot), ra
                last_bx, last_by, last_bz = bx, by, bz
            update_voxel(voxels, slot, vx, vy, vz, d, truncation_mm, inv_trunc, act,
                         active_weight_cap, max_weight, behind, n_i)
        t, vx, vy, vz, tmx, tmy, tmz, d = dda_step(vx, vy, vz, tmx, tmy, tmz, d, steps)
    if not act:
        return ra, rb
    # beyond the band: allocated (or staged) blocks only; a free run ends at a column edge
    end = span + carve_vox
    n_run, run_cx, run_cy = 0, 1 << 40, 0
    while t <= end:
        if not owned or mine or owner(vx, vy, cs) == tid:
            if (vx >> cs) != run_cx or (vy >> cs) != run_cy:
                n_run, run_cx, run_cy = 0, vx >> cs, vy >> cs
            bx, by, bz = vx >> BLOCK_SHIFT, vy >> BLOCK_SHIFT, vz >> BLOCK_SHIFT
            if bx != last_bx or by != last_by or bz != last_bz:
                slot = recent_slot(bx, by, bz, ra, rb)
                if slot < 0:
                    key = pack_key(bx, by, bz)
                    if owned:
                        slot = found_slot(key, table_keys, table_slots, base, staging)
                    else:
                        slot = hash_find(table_keys, table_slots, key)
                    if slot >= 0:
                        ra, rb = (bx, by, bz, slot), ra
                last_bx, last_by, last_bz = bx, by, bz
            n_run = carve_visit(voxels, slot, vx, vy, vz, truncation_mm, run, n_run, touched,
                                limit)
        t, vx, vy, vz, tmx, tmy, tmz, d = dda_step(vx, vy, vz, tmx, tmy, tmz, d, steps)
    return ra, rb
