"""The one ray walk of the TSDF kernels, shared (inlined) by the serial integrator
(:mod:`dm2.fusion.tsdf.kernels`) and the two-thread one (:mod:`dm2.fusion.tsdf.owned_kernels`).

:func:`fuse_batch` registers each point of a batch (:mod:`dm2.fusion.tsdf.point_rays`) and
:func:`walk_ray` walks its ray through the voxel grid with a 3-D DDA (Amanatides & Woo) from
``truncation`` in front of the measured point to ``truncation`` behind it, updating every voxel
it crosses with the projective signed distance (eqs 2-5 of the paper); an active ray then walks
on beyond its band through allocated blocks only, carving enclosed stale free space
(:mod:`dm2.fusion.tsdf.carve`).

One walk for both kernels: ``owned`` (a literal, so each kernel is compiled without the other's
tests) says whether the walk belongs to thread ``tid`` of the two-thread update, which updates
only the voxels of its own block columns and stages the blocks the field lacks; the serial walk
updates every voxel and allocates blocks in the field. Every voxel sees the same operations in
the same order either way, so the two-thread field is the serial one bit for bit.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from dm2.fusion.tsdf.block_hash import (
    BLOCK_SHIFT,
    MAX_NEW_BLOCKS_PER_RAY,
    hash_find,
    hash_get_or_insert,
    pack_key,
    recent_slot,
)
from dm2.fusion.tsdf.carve import CARVE_RUN_VOXELS, CARVE_TRUNCATIONS, carve_visit, walk_columns
from dm2.fusion.tsdf.point_rays import NO_POSE, point_ray, profile_pose

_FAR = 1 << 40  # a block coordinate no ray reaches: "no block looked up yet"


@njit(cache=True, inline="always")
def dda_start(ox, oy, oz, dx, dy, dz, r, truncation_mm, voxel_mm, inv_vox):
    """First voxel and DDA state of the band ``r +- truncation_mm`` of the ray from ``o`` along
    unit ``d``: ``(vx, vy, vz, span, tmx, tmy, tmz, sd)`` (voxel, the band's length ``span``
    [voxels], next crossings ``tm*`` [voxels], projective signed distance ``sd`` [mm] of the
    first voxel's centre: ``r`` minus its distance from the origin along the ray) and the
    ray's constant ``steps``: ``(stx, sty, stz, tdx, tdy, tdz, ddx, ddy, ddz)`` (steps ``st*``,
    crossing increments ``td*`` [voxels], change ``dd*`` [mm] of ``sd`` per step)."""
    t0 = r - truncation_mm
    t1 = r + truncation_mm
    sx0, sy0, sz0 = (ox + dx * t0) * inv_vox, (oy + dy * t0) * inv_vox, \
        (oz + dz * t0) * inv_vox
    vx, vy, vz = int(np.floor(sx0)), int(np.floor(sy0)), int(np.floor(sz0))
    span = (t1 - t0) * inv_vox
    stx = 1 if dx > 0 else -1
    sty = 1 if dy > 0 else -1
    stz = 1 if dz > 0 else -1
    big = 1e30
    tdx = abs(1.0 / dx) if dx != 0 else big
    tdy = abs(1.0 / dy) if dy != 0 else big
    tdz = abs(1.0 / dz) if dz != 0 else big
    tmx = ((vx + 1 - sx0) if dx > 0 else (sx0 - vx)) * tdx if dx != 0 else big
    tmy = ((vy + 1 - sy0) if dy > 0 else (sy0 - vy)) * tdy if dy != 0 else big
    tmz = ((vz + 1 - sz0) if dz > 0 else (sz0 - vz)) * tdz if dz != 0 else big
    sd = r - (((vx + 0.5) * voxel_mm - ox) * dx + ((vy + 0.5) * voxel_mm - oy) * dy
              + ((vz + 0.5) * voxel_mm - oz) * dz)
    steps = (stx, sty, stz, tdx, tdy, tdz,
             stx * voxel_mm * dx, sty * voxel_mm * dy, stz * voxel_mm * dz)
    return (vx, vy, vz, span, tmx, tmy, tmz, sd), steps


@njit(cache=True, inline="always")
def dda_step(steps, vx, vy, vz, tmx, tmy, tmz, sd):
    """Step to the next voxel along the axis whose boundary the ray crosses first; returns the
    new ray parameter ``t`` (voxel units), voxel, crossing parameters and signed distance."""
    stx, sty, stz, tdx, tdy, tdz, ddx, ddy, ddz = steps
    if tmx < tmy:
        if tmx < tmz:
            return tmx, vx + stx, vy, vz, tmx + tdx, tmy, tmz, sd - ddx
        return tmz, vx, vy, vz + stz, tmx, tmy, tmz + tdz, sd - ddz
    if tmy < tmz:
        return tmy, vx, vy + sty, vz, tmx, tmy + tdy, tmz, sd - ddy
    return tmz, vx, vy, vz + stz, tmx, tmy, tmz + tdz, sd - ddz


@njit(cache=True, inline="always")
def update_voxel(voxels, slot, vx, vy, vz, d, params, inv_trunc, act):
    """One voxel's update along a ray (paper eqs 2-5): projective signed distance ``d`` [mm]
    clamped to +-truncation, weight ``w_A = 1`` in the active region and ``w_I`` (1 in front,
    falling linearly behind the surface) elsewhere, the stored weight capped in the active
    region (``params``: :class:`~dm2.fusion.tsdf.bundles.FuseParams`)."""
    truncation_mm = params.truncation_mm
    if d > truncation_mm:
        d = truncation_mm
    elif d < -truncation_mm:
        d = -truncation_mm
    w = 1.0 if (act or d >= 0.0) else 1.0 + d * inv_trunc
    if w > 0.0:
        li = (vx & 7) + 8 * ((vy & 7) + 8 * (vz & 7))
        w_prev = voxels[slot, li, 1]
        if act and w_prev > params.active_weight_cap:
            w_prev = params.active_weight_cap
        w_new = w_prev + w
        voxels[slot, li, 0] = (w_prev * voxels[slot, li, 0] + w * d) / w_new
        voxels[slot, li, 1] = min(w_new, params.max_weight)


@njit(cache=True, nogil=True)
def _staged_slot(key, staged):
    """Field row of a block the field lacks: its row in the thread's reserved rows (staged
    now when new). Not inlined: the fusion loop stays small, and this path is rare."""
    return staged.base + hash_get_or_insert(key, staged.table_keys, staged.table_slots,
                                            staged.keys, staged.state)


@njit(cache=True, nogil=True)
def _found_slot(key, blocks, staged):
    """Field row of an allocated or staged block, -1 for neither (the carve beyond a ray's
    band allocates nothing)."""
    s = hash_find(blocks.table_keys, blocks.table_slots, key)
    if s >= 0:
        return s
    s = hash_find(staged.table_keys, staged.table_slots, key)
    return staged.base + s if s >= 0 else -1


@njit(cache=True, inline="always")
def band_slot(owned, key, blocks, staged):
    """Row of block ``key`` for the band, marked touched: the serial walk allocates a missing
    block in the field, a thread's walk stages it (marked when committed)."""
    if owned:
        s = hash_find(blocks.table_keys, blocks.table_slots, key)
        if s >= 0:
            blocks.touched[s] = True
            return s
        return _staged_slot(key, staged)
    s = hash_get_or_insert(key, blocks.table_keys, blocks.table_slots, blocks.block_keys,
                           blocks.state)
    blocks.touched[s] = True
    return s


@njit(cache=True, inline="always")
def carve_slot(owned, key, blocks, staged):
    """Row of block ``key`` beyond the band, -1 where it is not allocated (nor staged)."""
    if owned:
        return _found_slot(key, blocks, staged)
    return hash_find(blocks.table_keys, blocks.table_slots, key)


@njit(cache=True, inline="always")
def walk_ray(owned, owner, ray, act, params, consts, blocks, staged, run, recent):
    """Walk one ray: its band, then (``act``) the carve beyond it.

    ``owner = (tid, mine, cs)``: the walk updates a voxel when ``mine`` (the whole walk lies in
    one column of ``2**cs`` voxels that is the walker's) or its column is thread ``tid``'s
    (``(cx + cy) & 1 == tid``); the serial walk passes ``mine`` True. ``ray = (ox, oy, oz, dx,
    dy, dz, r)``, ``consts = (inv_vox, inv_trunc, carve_vox)``, ``run``: the carve's scratch,
    ``recent``: the two blocks looked up last, returned updated.
    A free run of the carve ends where the walk enters another column, as the two-thread walk
    sees it, so the serial walk does the same.
    """
    tid, mine, cs = owner
    ox, oy, oz, dx, dy, dz, r = ray
    inv_vox, inv_trunc, carve_vox = consts
    ra, rb = recent
    first, steps = dda_start(ox, oy, oz, dx, dy, dz, r, params.truncation_mm, params.voxel_mm,
                             inv_vox)
    vx, vy, vz, span, tmx, tmy, tmz, d = first
    last_bx, last_by, last_bz, slot = _FAR, 0, 0, -1
    t = 0.0
    while t <= span:
        if mine or ((vx >> cs) + (vy >> cs)) & 1 == tid:
            bx, by, bz = vx >> BLOCK_SHIFT, vy >> BLOCK_SHIFT, vz >> BLOCK_SHIFT
            if bx != last_bx or by != last_by or bz != last_bz:
                slot = recent_slot(bx, by, bz, ra, rb)
                if slot < 0:
                    slot = band_slot(owned, pack_key(bx, by, bz), blocks, staged)
                    ra, rb = (bx, by, bz, slot), ra
                last_bx, last_by, last_bz = bx, by, bz
            update_voxel(blocks.voxels, slot, vx, vy, vz, d, params, inv_trunc, act)
        t, vx, vy, vz, tmx, tmy, tmz, d = dda_step(steps, vx, vy, vz, tmx, tmy, tmz, d)
    if not act:
        return ra, rb
    # beyond the band: allocated blocks only; a free run ends at a column edge
    end = span + carve_vox
    n_run, run_cx, run_cy = 0, _FAR, 0
    while t <= end:
        if mine or ((vx >> cs) + (vy >> cs)) & 1 == tid:
            if (vx >> cs) != run_cx or (vy >> cs) != run_cy:
                n_run, run_cx, run_cy = 0, vx >> cs, vy >> cs
            bx, by, bz = vx >> BLOCK_SHIFT, vy >> BLOCK_SHIFT, vz >> BLOCK_SHIFT
            if bx != last_bx or by != last_by or bz != last_bz:
                slot = recent_slot(bx, by, bz, ra, rb)
                if slot < 0:
                    slot = carve_slot(owned, pack_key(bx, by, bz), blocks, staged)
                    if slot >= 0:
                        ra, rb = (bx, by, bz, slot), ra
                last_bx, last_by, last_bz = bx, by, bz
            n_run = carve_visit(blocks.voxels, slot, vx, vy, vz, params.truncation_mm, run,
                                n_run, blocks.touched, staged.base)
        t, vx, vy, vz, tmx, tmy, tmz, d = dda_step(steps, vx, vy, vz, tmx, tmy, tmz, d)
    return ra, rb


@njit(cache=True, inline="always")
def fuse_batch(owned, register, use_bounds, tid, col_shift, start, batch, params, blocks,
               staged, counts):
    """The one integration loop: the points of ``batch`` from index ``start`` on, each
    registered (``register``: profiles; else rays given in ``O``) and walked. ``owned``:
    thread ``tid``'s walk of the two-thread update, which skips rays wholly in the other
    thread's columns (``2**col_shift`` blocks wide) and stops when its staging area
    ``staged`` may not hold one more ray's blocks; the serial walk stops when the field's
    block arrays or hash table may not. Returns the index of the first point not handled
    (the batch's length when done).

    Signed distance ``d`` [mm] is positive in front of the measured point (free space towards
    the sensor) and negative behind it; ``voxels[slot, li, 0]`` is the signed distance,
    ``voxels[slot, li, 1]`` the weight.
    """
    inv_vox = 1.0 / params.voxel_mm
    inv_trunc = 1.0 / params.truncation_mm
    carve_mm = CARVE_TRUNCATIONS * params.truncation_mm
    consts = (inv_vox, inv_trunc, carve_mm * inv_vox)
    cs = BLOCK_SHIFT + col_shift
    capacity = blocks.voxels.shape[0]
    table_limit = blocks.table_keys.shape[0] // 2
    st_capacity = staged.keys.shape[0]
    run = np.empty((CARVE_RUN_VOXELS, 2), dtype=np.int64)
    offsets = batch.offsets
    pose = NO_POSE
    recent = ((_FAR, 0, 0, -1), (_FAR, 0, 0, -1))  # (bx, by, bz, slot) of two blocks
    for k in range(offsets.shape[0] - 1):
        if offsets[k + 1] <= start:
            continue
        if register:
            pose = profile_pose(batch.T_O_S, batch.spot_O, batch.axis_O, k)
        for i in range(max(offsets[k], start), offsets[k + 1]):
            if owned:
                if staged.state[0] + MAX_NEW_BLOCKS_PER_RAY > st_capacity:
                    return i
            elif blocks.state[0] + MAX_NEW_BLOCKS_PER_RAY > capacity or \
                    blocks.state[0] + MAX_NEW_BLOCKS_PER_RAY > table_limit:
                return i
            ok, ox, oy, oz, dx, dy, dz, r, act = point_ray(register, use_bounds, i, pose, batch,
                                                           params.truncation_mm, counts)
            if not ok:
                continue
            mine = True
            if owned:  # the columns of the walk (an active ray walks on beyond its band)
                cx0, cx1, cy0, cy1 = walk_columns(ox, oy, dx, dy, r, params.truncation_mm,
                                                  carve_mm if act else 0.0, inv_vox, cs)
                mine = cx0 == cx1 and cy0 == cy1
                if mine and ((cx0 + cy0) & 1) != tid:
                    continue  # the other thread's column
            recent = walk_ray(owned, (tid, mine, cs), (ox, oy, oz, dx, dy, dz, r), act, params,
                              consts, blocks, staged, run, recent)
    return offsets[offsets.shape[0] - 1]
