"""The walk along one sensor ray through the voxel grid (3-D DDA, Amanatides & Woo) and the
update of each voxel it crosses (paper eqs 2-5), shared by the serial TSDF kernel
(:func:`dm2.fusion.tsdf.kernels._fuse`) and the two-thread one
(:func:`dm2.fusion.tsdf.owned_kernels.fuse_owned`).

All three helpers are inlined into their callers (``inline="always"``), so both kernels run
the same operations in the same order and their fields are bit-identical. Voxel coordinates
``vx, vy, vz`` are integer indices (voxel ``v`` spans ``[v, v + 1) * voxel_mm`` [mm, O]).
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, inline="always")
def dda_start(ox, oy, oz, dx, dy, dz, r, truncation_mm, voxel_mm, inv_vox):
    """First voxel and DDA state (Amanatides & Woo) of the band ``r +- truncation_mm`` of the
    ray from ``(ox, oy, oz)`` [mm, O] along the unit ``(dx, dy, dz)``: ``vx, vy, vz, span, tmx,
    tmy, tmz, d, steps`` with the first voxel ``vx, vy, vz``, the band's length ``span``
    [voxels], the next crossings ``tm*`` [voxels] and the projective signed distance ``d`` [mm]
    of the first voxel's centre (``r`` minus its distance from the origin along the ray).
    ``steps`` holds the ray's constants for :func:`dda_step`: ``(stx, sty, stz, tdx, tdy, tdz,
    ddx, ddy, ddz)``, the voxel steps ``st*`` (+-1), the crossing increments ``td*`` [voxels]
    and the change ``dd*`` [mm] of ``d`` per step along each axis."""
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
    d = r - (((vx + 0.5) * voxel_mm - ox) * dx + ((vy + 0.5) * voxel_mm - oy) * dy
             + ((vz + 0.5) * voxel_mm - oz) * dz)
    return (vx, vy, vz, span, tmx, tmy, tmz, d,
            (stx, sty, stz, tdx, tdy, tdz,
             stx * voxel_mm * dx, sty * voxel_mm * dy, stz * voxel_mm * dz))


@njit(cache=True, inline="always")
def dda_step(vx, vy, vz, tmx, tmy, tmz, d, steps):
    """Step to the next voxel along the axis whose boundary the ray crosses first (``steps``:
    the ray's constants from :func:`dda_start`); returns the new ray parameter ``t`` (voxel
    units), voxel, crossing parameters and signed distance [mm]."""
    stx, sty, stz, tdx, tdy, tdz, ddx, ddy, ddz = steps
    if tmx < tmy:
        if tmx < tmz:
            return tmx, vx + stx, vy, vz, tmx + tdx, tmy, tmz, d - ddx
        return tmz, vx, vy, vz + stz, tmx, tmy, tmz + tdz, d - ddz
    if tmy < tmz:
        return tmy, vx, vy + sty, vz, tmx, tmy + tdy, tmz, d - ddy
    return tmz, vx, vy, vz + stz, tmx, tmy, tmz + tdz, d - ddz


@njit(cache=True, inline="always")
def update_voxel(voxels, slot, vx, vy, vz, d, truncation_mm, inv_trunc, act, active_weight_cap,
                 max_weight, behind_scale, n):
    """One voxel's update along a ray (paper eqs 2-5): projective signed distance ``d`` [mm]
    clamped to +-truncation, weight 1 in front of the surface and falling linearly behind it
    (``w_A`` in the active region and ``w_I`` elsewhere alike), times ``behind_scale`` behind
    it (0 behind a point on an occluding edge: :func:`dm2.fusion.tsdf.point_rays.behind_scale`),
    the stored weight capped in the active region. The ray stands for ``n`` measured points
    (:mod:`dm2.fusion.profile_merge`): the voxel is updated ``n`` times with that distance and
    weight, each update capped as a point's is, so at the weight caps too it ends as after ``n``
    rays with the mean's distance (the capped running mean weighs each new point by ``1 /
    (cap + 1)``; one update of ``n`` times the weight would weigh the run by ``n / (cap + n)``)."""
    if d > truncation_mm:
        d = truncation_mm
    elif d < -truncation_mm:
        d = -truncation_mm
    w = 1.0 if d >= 0.0 else (1.0 + d * inv_trunc) * behind_scale
    if w > 0.0:
        li = (vx & 7) + 8 * ((vy & 7) + 8 * (vz & 7))
        w_prev = voxels[slot, li, 1]
        tsdf = voxels[slot, li, 0]
        for _ in range(n):
            if act and w_prev > active_weight_cap:
                w_prev = active_weight_cap
            w_new = w_prev + w
            tsdf = (w_prev * tsdf + w * d) / w_new
            w_prev = min(w_new, max_weight)
        voxels[slot, li, 0] = tsdf
        voxels[slot, li, 1] = w_prev
