"""How one powder packet's volume lands on the twin's height field: a small Gaussian splat.

:func:`splat` adds a packet's volume around the point where it hit
(:func:`twin.world.deposition_kernels.spray_step`), volume-conserving, and keeps the field's
per-block height bounds and changed-cell box up to date (:func:`raise_bounds`).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from twin.world.heightfield_kernels import BLOCK

SPLAT_RADIUS_CELLS = 2  # a packet spreads over (2r+1)^2 cells
SPLAT_SIGMA_CELLS = 1.0  # Gaussian spread of one packet's splat, in cells
# exp(-d^2 / 2s^2) for d = 0 .. SPLAT_RADIUS_CELLS (a compile-time constant of the kernels)
_SPLAT_G = np.exp(-np.arange(SPLAT_RADIUS_CELLS + 1.0) ** 2
                  / (2.0 * SPLAT_SIGMA_CELLS * SPLAT_SIGMA_CELLS))


@njit(cache=True, inline="always")
def _splat_row(H, j, i, wy, d0, d1, d2, d3, d4, top):
    """Add ``dk * wy`` to cell ``(j, i + k)``, k = 0..4; returns the highest height so far."""
    h = H[j, i] + d0 * wy
    H[j, i] = h
    top = max(top, h)
    h = H[j, i + 1] + d1 * wy
    H[j, i + 1] = h
    top = max(top, h)
    h = H[j, i + 2] + d2 * wy
    H[j, i + 2] = h
    top = max(top, h)
    h = H[j, i + 3] + d3 * wy
    H[j, i + 3] = h
    top = max(top, h)
    h = H[j, i + 4] + d4 * wy
    H[j, i + 4] = h
    return max(top, h)


@njit(cache=True)
def raise_bounds(bmax, zmax, dirty, j_lo, j_hi, i_lo, i_hi, top):
    """Raise the bounds of the blocks holding nodes ``j_lo..j_hi x i_lo..i_hi`` (and the
    field's top) to ``top``, and add the nodes to the changed-cell box ``dirty``."""
    for bj in range(j_lo // BLOCK, (j_hi + 1) // BLOCK + 1):
        for bi in range(i_lo // BLOCK, (i_hi + 1) // BLOCK + 1):
            if top > bmax[bj, bi]:
                bmax[bj, bi] = top
    if top > zmax[0]:
        zmax[0] = top
    dirty[0] = min(dirty[0], j_lo)
    dirty[1] = max(dirty[1], j_hi)
    dirty[2] = min(dirty[2], i_lo)
    dirty[3] = max(dirty[3], i_hi)


@njit(cache=True)
def splat(H, bmax, zmax, dirty, cell, x, y, vol, w, unrolled=True):
    """Add ``vol`` [mm^3] at ``(x, y)`` as a small Gaussian splat (sigma one cell, 5 x 5 cells).

    A packet stands for many particles that flatten on impact; spreading it over a few cells
    keeps single packets from building cell-sized spikes that then shadow their neighbours
    (ballistic columnar growth, far rougher than a cold-spray deposit). Weights are normalised
    over the cells that exist, so volume is conserved exactly. The Gaussian is separable, so
    ``w`` (scratch, at least ``2 * (2 * SPLAT_RADIUS_CELLS + 1)`` floats) holds the x and the
    y weights. Normalised weights only need ``exp(-(d - f)^2 / 2s^2)`` up to a common factor,
    i.e. ``exp(-d^2 / 2s^2) * exp(f / s^2)^d`` for offset ``d`` from the nearest centre and
    sub-cell offset ``f``: two exponentials per axis instead of five. The cells written are
    added to the changed-cell box ``dirty`` ([j_min, j_max, i_min, i_max]). A splat with all
    its cells on the grid takes an unrolled path of the same operations (the same bits; False
    ``unrolled`` keeps the general path).
    """
    ny, nx = H.shape
    u = x / cell - 0.5
    v = y / cell - 0.5
    ic = int(math.floor(u + 0.5))
    jc = int(math.floor(v + 0.5))
    r = SPLAT_RADIUS_CELLS
    m = 2 * r + 1
    inv2s2 = 1.0 / (2.0 * SPLAT_SIGMA_CELLS * SPLAT_SIGMA_CELLS)
    ex = math.exp(2.0 * (u - ic) * inv2s2)
    ey = math.exp(2.0 * (v - jc) * inv2s2)
    exi = 1.0 / ex
    eyi = 1.0 / ey
    if unrolled and r == 2 and 2 <= ic < nx - 2 and 2 <= jc < ny - 2:  # all 25 on the grid
        g1 = _SPLAT_G[1]
        g2 = _SPLAT_G[2]
        x0, x1, x3, x4 = g2 * (exi * exi), g1 * exi, g1 * ex, g2 * (ex * ex)
        y0, y1, y3, y4 = g2 * (eyi * eyi), g1 * eyi, g1 * ey, g2 * (ey * ey)
        sx = (((x0 + x1) + 1.0) + x3) + x4
        sy = (((y0 + y1) + 1.0) + y3) + y4
        dh = vol / (cell * cell * sx * sy)
        d0, d1, d3, d4 = dh * x0, dh * x1, dh * x3, dh * x4  # (dh * wx) * wy, as below
        top = -np.inf
        top = _splat_row(H, jc - 2, ic - 2, y0, d0, d1, dh, d3, d4, top)
        top = _splat_row(H, jc - 1, ic - 2, y1, d0, d1, dh, d3, d4, top)
        top = _splat_row(H, jc, ic - 2, 1.0, d0, d1, dh, d3, d4, top)
        top = _splat_row(H, jc + 1, ic - 2, y3, d0, d1, dh, d3, d4, top)
        top = _splat_row(H, jc + 2, ic - 2, y4, d0, d1, dh, d3, d4, top)
        raise_bounds(bmax, zmax, dirty, jc - 2, jc + 2, ic - 2, ic + 2, top)
        return
    # w[:m] holds x, w[m:2m] holds y; centre first, then outwards in both directions
    w[r] = 1.0 if 0 <= ic < nx else 0.0
    w[m + r] = 1.0 if 0 <= jc < ny else 0.0
    px = 1.0
    nxp = 1.0
    py = 1.0
    nyp = 1.0
    for d in range(1, r + 1):
        g = _SPLAT_G[d]
        px *= ex
        nxp *= exi
        py *= ey
        nyp *= eyi
        w[r + d] = g * px if ic + d < nx else 0.0
        w[r - d] = g * nxp if ic - d >= 0 else 0.0
        w[m + r + d] = g * py if jc + d < ny else 0.0
        w[m + r - d] = g * nyp if jc - d >= 0 else 0.0
    sx = 0.0
    sy = 0.0
    for d in range(m):
        sx += w[d]
        sy += w[m + d]
    if sx <= 0.0 or sy <= 0.0:
        return
    dh = vol / (cell * cell * sx * sy)
    top = -np.inf
    for dj in range(-r, r + 1):
        wy = w[m + dj + r]
        if wy == 0.0:
            continue
        j = jc + dj
        for di in range(-r, r + 1):
            wx = w[di + r]
            if wx == 0.0:
                continue
            i = ic + di
            h = H[j, i] + dh * wx * wy
            H[j, i] = h
            if h > top:
                top = h
    # the splat's highest node bounds every block its nodes touch (a valid, slightly looser
    # bound than node by node, for a fraction of the work)
    raise_bounds(bmax, zmax, dirty, max(jc - r, 0), min(jc + r, ny - 1), max(ic - r, 0),
                  min(ic + r, nx - 1), top)
