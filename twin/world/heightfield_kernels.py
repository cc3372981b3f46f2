"""Numba kernels for :class:`twin.world.heightfield.HeightField`: exact bilinear ray casting.

Grid coordinates
----------------
Heights ``H[j, i]`` sit at cell centres ``x = (i + 0.5) * c``, ``y = (j + 0.5) * c``. The kernels
work in the shifted grid coordinate ``U = x / c + 0.5`` (``V`` likewise), in which node ``k``
lies at ``U = k + 1`` and the plate spans ``U in [0.5, nx + 0.5]``. Patch ``pi`` covers
``U in [pi, pi + 1]`` for ``pi = 0 .. nx`` and interpolates bilinearly between nodes
``pi - 1`` and ``pi``, clamped to ``[0, nx - 1]`` (so the outer half cells are flat
extensions of the border values). The solid is ``{(x, y, z): (x, y) on the plate,
-thickness <= z <= h(x, y)}``; a ray hits its boundary where it first enters it.

Acceleration: a coarse grid of ``BLOCK x BLOCK`` patches keeps an upper bound of the heights
in each block; the ray walks the coarse grid and descends into a block only where its height
range reaches the block's bound, then walks that block's patches and solves the exact
quadratic ray/bilinear-patch equation in each candidate patch.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from dm2.core.tolerances import INTERVAL_NUDGE, NEAR_ZERO, RELATIVE_ZERO, TINY_DIVISOR_FLOOR

BLOCK = 8


@njit(cache=True)
def _node(H, j, i):
    ny, nx = H.shape
    if i < 0:
        i = 0
    elif i > nx - 1:
        i = nx - 1
    if j < 0:
        j = 0
    elif j > ny - 1:
        j = ny - 1
    return H[j, i]


@njit(cache=True)
def bilinear_height(H, cell, x, y):
    """Height of the bilinear surface at ``(x, y)`` [mm]; NaN outside the plate."""
    ny, nx = H.shape
    U = x / cell + 0.5
    V = y / cell + 0.5
    if not (0.5 <= U <= nx + 0.5 and 0.5 <= V <= ny + 0.5):
        return np.nan
    pi = min(int(np.floor(U)), nx)
    pj = min(int(np.floor(V)), ny)
    s = U - pi
    r = V - pj
    h00 = _node(H, pj - 1, pi - 1)
    h10 = _node(H, pj - 1, pi)
    h01 = _node(H, pj, pi - 1)
    h11 = _node(H, pj, pi)
    return h00 * (1 - s) * (1 - r) + h10 * s * (1 - r) + h01 * (1 - s) * r + h11 * s * r


@njit(cache=True, nogil=True)
def compute_block_max(H, out):
    """Fill ``out[bj, bi]`` with the maximum node height of every patch in the block."""
    ny, nx = H.shape
    out[:, :] = -np.inf
    for k in range(ny):
        for m in range(nx):
            raise_block_max(out, k, m, H[k, m])


@njit(cache=True)
def raise_block_max(bmax, k, m, h):
    """Keep the block bounds valid after node ``(k, m)`` rose to ``h``."""
    for pj in range(k, k + 2):
        for pi in range(m, m + 2):
            bj = pj // BLOCK
            bi = pi // BLOCK
            if h > bmax[bj, bi]:
                bmax[bj, bi] = h


@njit(cache=True)
def _patch_hit(H, pi, pj, U0, V0, z0, dU, dV, dz, ta, tb):
    """First ``t`` in ``[ta, tb]`` where the ray meets patch ``(pi, pj)`` from above, or inf."""
    ny, nx = H.shape
    if 0 < pi < nx and 0 < pj < ny:  # all four nodes inside: no clamping
        h00 = H[pj - 1, pi - 1]
        h10 = H[pj - 1, pi]
        h01 = H[pj, pi - 1]
        h11 = H[pj, pi]
    else:
        h00 = _node(H, pj - 1, pi - 1)
        h10 = _node(H, pj - 1, pi)
        h01 = _node(H, pj, pi - 1)
        h11 = _node(H, pj, pi)
    za = z0 + dz * ta
    zb = z0 + dz * tb
    hmax = max(max(h00, h10), max(h01, h11))
    if za > hmax and zb > hmax:
        return np.inf
    s = U0 + dU * ta - pi
    r = V0 + dV * ta - pj
    B = h10 - h00
    C = h01 - h00
    D = h11 - h10 - h01 + h00
    # f(tau) = ray z - surface z, tau = t - ta: a0 + a1 tau + a2 tau^2
    a0 = za - (h00 + B * s + C * r + D * s * r)
    if a0 <= 0.0:
        return ta
    a1 = dz - (B * dU + C * dV + D * (s * dV + r * dU))
    a2 = -D * dU * dV
    span = tb - ta
    best = np.inf
    if abs(a2) * span < RELATIVE_ZERO * (abs(a1) + TINY_DIVISOR_FLOOR) or a2 == 0.0:
        if a1 < 0.0:
            best = -a0 / a1
    else:
        disc = a1 * a1 - 4.0 * a2 * a0
        if disc >= 0.0:
            sq = np.sqrt(disc)
            q = -0.5 * (a1 + sq) if a1 >= 0.0 else -0.5 * (a1 - sq)
            r1 = q / a2
            r2 = a0 / q if q != 0.0 else np.inf
            if r1 > r2:
                r1, r2 = r2, r1
            if r1 >= 0.0:
                best = r1
            elif r2 >= 0.0:
                best = r2
    if best <= span + RELATIVE_ZERO * (1.0 + span):
        return ta + min(best, span)
    return np.inf


@njit(cache=True)
def _slab(o, d, lo, hi, t0, t1):
    if abs(d) < NEAR_ZERO:
        if o < lo or o > hi:
            return 1.0, 0.0
        return t0, t1
    ta = (lo - o) / d
    tb = (hi - o) / d
    if ta > tb:
        ta, tb = tb, ta
    return max(t0, ta), min(t1, tb)


@njit(cache=True)
def ray_one(H, bmax, cell, thickness, zmax, ox, oy, oz, dx, dy, dz, max_range):
    """Distance [mm] along the unit ray to the first hit of the solid, or inf."""
    ny, nx = H.shape
    U0 = ox / cell + 0.5
    V0 = oy / cell + 0.5
    dU = dx / cell
    dV = dy / cell
    t0, t1 = _slab(U0, dU, 0.5, nx + 0.5, 0.0, max_range)
    t0, t1 = _slab(V0, dV, 0.5, ny + 0.5, t0, t1)
    t0, t1 = _slab(oz, dz, -thickness, zmax, t0, t1)
    if not t0 <= t1:
        return np.inf
    nbx = bmax.shape[1]
    nby = bmax.shape[0]
    bsize = float(BLOCK)
    # coarse walk over blocks
    tm = 0.5 * (t0 + t1) if t1 - t0 < INTERVAL_NUDGE else t0 + INTERVAL_NUDGE * (t1 - t0)
    bi = min(max(int(np.floor((U0 + dU * tm) / bsize)), 0), nbx - 1)
    bj = min(max(int(np.floor((V0 + dV * tm) / bsize)), 0), nby - 1)
    stepbi = 1 if dU > 0 else -1
    stepbj = 1 if dV > 0 else -1
    t = t0
    while t <= t1:
        # exit of this block
        if dU > NEAR_ZERO:
            tu = ((bi + 1) * bsize - U0) / dU
        elif dU < -NEAR_ZERO:
            tu = (bi * bsize - U0) / dU
        else:
            tu = np.inf
        if dV > NEAR_ZERO:
            tv = ((bj + 1) * bsize - V0) / dV
        elif dV < -NEAR_ZERO:
            tv = (bj * bsize - V0) / dV
        else:
            tv = np.inf
        tb = min(min(tu, tv), t1)
        za = oz + dz * t
        zb = oz + dz * tb
        if not (za > bmax[bj, bi] and zb > bmax[bj, bi]):
            hit = _walk_block(H, bi, bj, U0, V0, oz, dU, dV, dz, t, tb, bmax[bj, bi])
            if hit < np.inf:
                return hit
        if tb >= t1:
            break
        t = tb
        if tu <= tv:
            bi += stepbi
        else:
            bj += stepbj
        if bi < 0 or bi >= nbx or bj < 0 or bj >= nby:
            break
    return np.inf


@njit(cache=True)
def _walk_block(H, bi, bj, U0, V0, z0, dU, dV, dz, ta, tb, top):
    """First hit in block ``(bi, bj)`` (height bound ``top``) between ``ta`` and ``tb``, patch
    by patch; a ray that does not descend leaves as soon as it is above ``top``."""
    ny, nx = H.shape
    tm = ta + INTERVAL_NUDGE * (tb - ta) if tb > ta else ta
    lo_i = bi * BLOCK
    hi_i = min(lo_i + BLOCK - 1, nx)
    lo_j = bj * BLOCK
    hi_j = min(lo_j + BLOCK - 1, ny)
    pi = min(max(int(np.floor(U0 + dU * tm)), lo_i), hi_i)
    pj = min(max(int(np.floor(V0 + dV * tm)), lo_j), hi_j)
    t = ta
    while True:
        if dU > NEAR_ZERO:
            tu = (pi + 1 - U0) / dU
        elif dU < -NEAR_ZERO:
            tu = (pi - U0) / dU
        else:
            tu = np.inf
        if dV > NEAR_ZERO:
            tv = (pj + 1 - V0) / dV
        elif dV < -NEAR_ZERO:
            tv = (pj - V0) / dV
        else:
            tv = np.inf
        te = min(min(tu, tv), tb)
        hit = _patch_hit(H, pi, pj, U0, V0, z0, dU, dV, dz, t, te)
        if hit < np.inf:
            return hit
        if te >= tb:
            return np.inf
        t = te
        if dz >= 0.0 and z0 + dz * t > top:  # above every node of the block, and rising
            return np.inf
        if tu <= tv:
            pi += 1 if dU > 0 else -1
        else:
            pj += 1 if dV > 0 else -1
        if pi < lo_i or pi > hi_i or pj < lo_j or pj > hi_j:
            return np.inf


@njit(cache=True, nogil=True)
def raycast_serial(H, bmax, cell, thickness, zmax, origins, dirs, max_range, out):
    for k in range(origins.shape[0]):
        out[k] = ray_one(H, bmax, cell, thickness, zmax, origins[k, 0], origins[k, 1],
                         origins[k, 2], dirs[k, 0], dirs[k, 1], dirs[k, 2], max_range)


@njit(cache=True, parallel=True, nogil=True)
def raycast_parallel(H, bmax, cell, thickness, zmax, origins, dirs, max_range, out):
    for k in prange(origins.shape[0]):
        out[k] = ray_one(H, bmax, cell, thickness, zmax, origins[k, 0], origins[k, 1],
                         origins[k, 2], dirs[k, 0], dirs[k, 1], dirs[k, 2], max_range)


@njit(cache=True, nogil=True)
def heights_at(H, cell, xy, out):
    for k in range(xy.shape[0]):
        out[k] = bilinear_height(H, cell, xy[k, 0], xy[k, 1])


@njit(cache=True)
def normal_at(H, cell, x, y):
    """Unit upward normal of the bilinear surface at ``(x, y)`` (exact patch gradient)."""
    ny, nx = H.shape
    U = min(max(x / cell + 0.5, 0.5), nx + 0.5)
    V = min(max(y / cell + 0.5, 0.5), ny + 0.5)
    pi = min(int(np.floor(U)), nx)
    pj = min(int(np.floor(V)), ny)
    s = U - pi
    r = V - pj
    h00 = _node(H, pj - 1, pi - 1)
    h10 = _node(H, pj - 1, pi)
    h01 = _node(H, pj, pi - 1)
    h11 = _node(H, pj, pi)
    # a clamped border half patch is flat across the clamp
    ws = 0.0 if (pi == 0 or pi == nx) else 1.0
    wr = 0.0 if (pj == 0 or pj == ny) else 1.0
    gx = ws * ((h10 - h00) * (1 - r) + (h11 - h01) * r) / cell
    gy = wr * ((h01 - h00) * (1 - s) + (h11 - h10) * s) / cell
    n = np.sqrt(gx * gx + gy * gy + 1.0)
    return -gx / n, -gy / n, 1.0 / n


@njit(cache=True, nogil=True)
def normals_at(H, cell, xy, out):
    for k in range(xy.shape[0]):
        nx_, ny_, nz_ = normal_at(H, cell, xy[k, 0], xy[k, 1])
        out[k, 0] = nx_
        out[k, 1] = ny_
        out[k, 2] = nz_
