"""Numba kernels of the near-net reference (:mod:`dm2.reference.model`).

One call of :func:`integrate_states` takes a batch of flange poses, turns each into the spray
spot and axis in ``O``, splits every move into short pieces and deposits a Gaussian footprint
per piece onto the height map in place. Nothing the size of the map is allocated per call: the
footprint is computed into a scratch buffer owned by the reference, then added.

Per spot (see :mod:`dm2.reference.model` for the model):

* the spray axis is ray-marched from the nozzle exit onto the reference's own surface, so a
  tilted spray lands where its axis meets the current surface, not at the programmed point;
* a tilted spray's footprint is taken along its rays: each cell's offset from the axis is
  that of its own surface point (``dz`` above or below the impact point), so a cell below the
  impact point catches the rays ``dz * tan(tilt)`` farther down the tilt, not those that a flat
  plate at the impact height would (a tilted contour over a rim or a mound);
* the spray angle of every footprint cell is taken against that cell's own surface normal
  (central difference over ``slope_cells``) or, with ``slope_cells == 0``, against ``+z_O``.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit

from dm2.core.tolerances import DOWNWARD_COS, NEAR_ZERO
from dm2.reference.tilted_band import NO_BAND, row_span, tilted_band

MARCH_REFINE_STEPS = 6  # bisections after the march brackets the surface (cell / 64)


class Spray(NamedTuple):
    """The deposition model of one call, bundled for the kernels (numba takes a named tuple)."""

    v_dot: float  # deposited volume rate [mm^3/s]
    zeta0: float  # deposition efficiency at normal incidence [-]
    theta_c: float  # critical spray angle [rad]
    sigma: float  # footprint standard deviation [mm]
    n_sigma: float  # footprint truncated at this many sigma [-]
    slope_cells: int  # central-difference half width of the surface normal [cells], 0: +z_O
    back_mm: float  # nozzle exit behind the spot along the axis (the standoff) [mm]
    lut: np.ndarray  # (n,) efficiency over cos theta in [0, 1] (:func:`efficiency_table`)


class HeightMap(NamedTuple):
    """The reference's height map and what the kernels keep beside it."""

    h: np.ndarray  # (ny, nx) float64 heights [mm], cell-centred, updated in place
    cell: float  # cell size [mm]
    zmax: np.ndarray  # (1,) float64 the map's highest value so far [mm], kept up to date
    scratch: np.ndarray  # footprint buffer: at least its cells plus nx + ny + 2


@njit(cache=True)
def bilinear(h, cell, x, y):
    """Bilinear height of the cell-centred grid ``h`` at ``(x, y)``, clamped at the border."""
    ny, nx = h.shape
    fx = min(max(x / cell - 0.5, 0.0), nx - 1.0)
    fy = min(max(y / cell - 0.5, 0.0), ny - 1.0)
    i0 = min(int(fx), nx - 2)
    j0 = min(int(fy), ny - 2)
    tx = fx - i0
    ty = fy - j0
    return ((1 - tx) * (1 - ty) * h[j0, i0] + tx * (1 - ty) * h[j0, i0 + 1]
            + (1 - tx) * ty * h[j0 + 1, i0] + tx * ty * h[j0 + 1, i0 + 1])


@njit(cache=True)
def efficiency(cos_t, zeta0, theta_c):
    """``zeta0 * cos^2(pi/2 * (theta / theta_c)^2)`` for ``theta = acos(cos_t) < theta_c``."""
    th = math.acos(min(max(cos_t, -1.0), 1.0)) / theta_c
    if th >= 1.0:
        return 0.0
    c = math.cos(0.5 * math.pi * th * th)
    return zeta0 * c * c


def efficiency_table(zeta0: float, theta_c: float, n: int = 4097,
                     cos_exponent: float = 0.0) -> np.ndarray:
    """:func:`efficiency` times ``cos(theta) ** cos_exponent`` at ``n`` evenly spaced
    ``cos theta`` in [0, 1]."""
    cos_t = np.linspace(0.0, 1.0, n)
    return np.array([efficiency(c, zeta0, theta_c) for c in cos_t]) * cos_t ** cos_exponent


@njit(cache=True)
def spots_from_poses(T_B_F, T_F_O, spot_B, axis_B, out_spot, out_axis):
    """Spot and unit spray axis in ``O`` of each flange pose ``T_B_F`` (m, 4, 4), written to
    ``out_spot`` / ``out_axis`` (at least (m, 3)): ``p_O = R^T (p_B - t)`` of
    ``T_B_O = T_B_F @ T_F_O``."""
    for k in range(T_B_F.shape[0]):
        R = np.empty((3, 3))
        t = np.empty(3)
        for r in range(3):
            for c in range(3):
                R[r, c] = (T_B_F[k, r, 0] * T_F_O[0, c] + T_B_F[k, r, 1] * T_F_O[1, c]
                           + T_B_F[k, r, 2] * T_F_O[2, c])
            t[r] = (T_B_F[k, r, 0] * T_F_O[0, 3] + T_B_F[k, r, 1] * T_F_O[1, 3]
                    + T_B_F[k, r, 2] * T_F_O[2, 3] + T_B_F[k, r, 3])
        for c in range(3):
            out_spot[k, c] = (R[0, c] * (spot_B[0] - t[0]) + R[1, c] * (spot_B[1] - t[1])
                              + R[2, c] * (spot_B[2] - t[2]))
            out_axis[k, c] = R[0, c] * axis_B[0] + R[1, c] * axis_B[1] + R[2, c] * axis_B[2]


@njit(cache=True)
def march_to_surface(h, cell, zmax, ox, oy, oz, ax, ay, az, t_max):
    """Distance along the unit axis from ``o`` to the first crossing of the height map, or
    ``-1.0`` when the ray stays above it up to ``t_max`` (or does not point down)."""
    if az > -DOWNWARD_COS:
        return -1.0
    t = 0.0
    if oz > zmax:  # nothing above zmax: start the march there
        t = (zmax - oz) / az
    if t > 0.0 and oz + t * az < bilinear(h, cell, ox + t * ax, oy + t * ay):
        t = 0.0  # zmax is stale (the map was written from outside): march from the nozzle
    if oz + t * az < bilinear(h, cell, ox + t * ax, oy + t * ay):
        return t  # the nozzle itself is inside the material
    step = 0.5 * cell
    while t < t_max:
        t1 = min(t + step, t_max)
        if oz + t1 * az <= bilinear(h, cell, ox + t1 * ax, oy + t1 * ay):
            lo = t
            hi = t1
            for _ in range(MARCH_REFINE_STEPS):
                mid = 0.5 * (lo + hi)
                if oz + mid * az <= bilinear(h, cell, ox + mid * ax, oy + mid * ay):
                    hi = mid
                else:
                    lo = mid
            return 0.5 * (lo + hi)
        t = t1
    return -1.0


@njit(cache=True)
def deposit_spot(hm, px, py, pz, ax, ay, az, dt, spray):
    """Deposit ``dt`` seconds of ``spray`` (:class:`Spray`) aimed at ``p`` along ``a`` onto
    the map ``hm`` (:class:`HeightMap`); returns the volume [mm^3]."""
    h, cell, zmax, scratch = hm.h, hm.cell, hm.zmax, hm.scratch
    v_dot, zeta0, theta_c, sigma = spray.v_dot, spray.zeta0, spray.theta_c, spray.sigma
    n_sigma, slope_cells, back_mm, lut = spray.n_sigma, spray.slope_cells, spray.back_mm, spray.lut
    ny, nx = h.shape
    if dt <= 0.0 or az >= 0.0:
        return 0.0
    ox, oy, oz = px - back_mm * ax, py - back_mm * ay, pz - back_mm * az
    t_max = (oz - min(pz, 0.0) + n_sigma * sigma) / -az  # well below the spot and the plate
    t = march_to_surface(h, cell, zmax[0], ox, oy, oz, ax, ay, az, t_max)
    if t >= 0.0:
        px, py, pz = ox + t * ax, oy + t * ay, oz + t * az
    inv2s2 = 1.0 / (2.0 * sigma * sigma)
    amp = v_dot * dt / (2.0 * math.pi * sigma * sigma) * abs(az)
    tilted = ax * ax + ay * ay > NEAR_ZERO
    reach = n_sigma * sigma / max(abs(az), 0.2)
    if tilted:  # a cell dz below (above) the impact point catches rays dz * tan(tilt) on
        dz_most = max(pz, zmax[0] - pz, 0.0)
        reach = min(reach + dz_most * math.sqrt(ax * ax + ay * ay) / abs(az),
                    n_sigma * sigma / 0.2)
    i_lo = max(int((px - reach) / cell), 0)
    i_hi = min(int((px + reach) / cell) + 1, nx - 1)
    j_lo = max(int((py - reach) / cell), 0)
    j_hi = min(int((py + reach) / cell) + 1, ny - 1)
    w = i_hi - i_lo + 1
    if i_hi < i_lo or j_hi < j_lo:
        return 0.0
    lim2 = (n_sigma * sigma) ** 2
    zeta_flat = efficiency(-az, zeta0, theta_c)
    total = 0.0
    zeta_cos = max(math.cos(theta_c), 0.0)
    # a vertical axis (infill) makes the Gaussian separable:
    # exp(-d2 / 2s^2) = ex[i] * ey[j]; the tail of ``scratch`` holds ex and ey
    separable = not tilted
    off = scratch.shape[0] - (nx + ny + 2)
    if separable:
        for i in range(i_lo, i_hi + 1):
            rx = (i + 0.5) * cell - px
            scratch[off + i - i_lo] = math.exp(-rx * rx * (1.0 - ax * ax) * inv2s2)
        for j in range(j_lo, j_hi + 1):
            ry = (j + 0.5) * cell - py
            scratch[off + w + j - j_lo] = math.exp(-ry * ry * (1.0 - ay * ay) * inv2s2)
    band = tilted_band(px, py, pz, ax, ay, az, zmax[0], n_sigma * sigma) if tilted else NO_BAND
    for j in range(j_lo, j_hi + 1):  # pass 1: the footprint on the surface as it was
        ry = (j + 0.5) * cell - py
        jm = max(j - slope_cells, 0)
        jp = min(j + slope_cells, ny - 1)
        ey = scratch[off + w + j - j_lo] if separable else 0.0
        ia, ib = row_span(band, ry, px, cell, i_lo, i_hi) if tilted else (i_lo, i_hi)
        for i in range(ia, ib + 1):
            rx = (i + 0.5) * cell - px
            if tilted:  # the ray through the cell's surface point, off the axis by r_perp
                rz = h[j, i] - pz
                along = rx * ax + ry * ay + rz * az
                d2 = rx * rx + ry * ry + rz * rz - along * along
            else:
                along = rx * ax + ry * ay
                d2 = rx * rx + ry * ry - along * along
            s = (j - j_lo) * w + (i - i_lo)
            if d2 > lim2:
                scratch[s] = 0.0
                continue
            zeta = zeta_flat
            if slope_cells > 0:  # spray angle against this cell's surface normal
                im = max(i - slope_cells, 0)
                ip = min(i + slope_cells, nx - 1)
                gx = (h[j, ip] - h[j, im]) / (max(ip - im, 1) * cell)
                gy = (h[jp, i] - h[jm, i]) / (max(jp - jm, 1) * cell)
                cos_t = (ax * gx + ay * gy - az) / math.sqrt(gx * gx + gy * gy + 1.0)
                zeta = (lut[int(cos_t * (lut.shape[0] - 1) + 0.5)] if cos_t > zeta_cos else 0.0)
                if tilted:  # the rays a cell's sloped patch catches, per horizontal area:
                    # |n . a| / n_z (|a_z| on a flat cell, the factor in amp), so the
                    # footprint keeps its volume on any surface the rays reach once
                    zeta *= max(ax * gx + ay * gy - az, 0.0) / abs(az)
            g = scratch[off + i - i_lo] * ey if separable else math.exp(-d2 * inv2s2)
            dz = amp * zeta * g
            scratch[s] = dz
            total += dz
    top = zmax[0]
    for j in range(j_lo, j_hi + 1):  # pass 2: add it
        ry = (j + 0.5) * cell - py
        ia, ib = row_span(band, ry, px, cell, i_lo, i_hi) if tilted else (i_lo, i_hi)
        for i in range(ia, ib + 1):
            dz = scratch[(j - j_lo) * w + (i - i_lo)]
            if dz != 0.0:
                h[j, i] += dz
                if h[j, i] > top:
                    top = h[j, i]
    zmax[0] = top
    return total * cell * cell


@njit(cache=True, nogil=True)
def flush_pending(hm, last, spray):
    """Deposit the pending piece held in ``last[8:16]`` (if any) and clear it; returns volume."""
    acc_dt = last[8]
    if acc_dt <= 0.0:
        return 0.0
    ax, ay, az = last[13], last[14], last[15]
    an = math.sqrt(ax * ax + ay * ay + az * az)
    vol = deposit_spot(hm, last[10] / acc_dt, last[11] / acc_dt, last[12] / acc_dt,
                       ax / an, ay / an, az / an, acc_dt, spray)
    for c in range(8, 16):
        last[c] = 0.0
    return vol


@njit(cache=True, nogil=True)
def integrate_states(hm, stamps, T_B_F, on, T_F_O, spot_B, axis_B, last, buf_spot, buf_axis,
                     spray, max_gap_s, max_piece_s):
    """Deposit ``spray`` (:class:`Spray`) onto the map ``hm`` (:class:`HeightMap`) along the
    moves into each of the robot states ``(stamps, T_B_F, on)``.

    ``last`` (16,) holds ``(valid, stamp, spot xyz, axis xyz)`` of the state before this batch
    and the pending piece ``(dt, length, dt-weighted spot xyz, dt-weighted axis xyz)``; it is
    updated. ``buf_spot`` / ``buf_axis`` (at least (m, 3)) are scratch. The path is cut into
    pieces of about ``sigma / 4`` (or ``max_piece_s``), one spot per piece at its time-weighted
    centre: moves shorter than that are gathered (a 250 Hz stream moves 0.1 mm per state),
    longer ones split. A piece still open at the end of the batch stays pending, so the result
    does not depend on how the states are batched. Returns ``(volume [mm^3], gaps skipped)``.
    """
    m = stamps.shape[0]
    spots_from_poses(T_B_F, T_F_O, spot_B, axis_B, buf_spot, buf_axis)
    piece = spray.sigma / 4.0
    total = 0.0
    gaps = 0
    for k in range(m):
        if last[0] > 0.0:
            dt = stamps[k] - last[1]
            if dt > max_gap_s or not on[k] or dt <= 0.0:
                if dt > max_gap_s:
                    gaps += 1
                if dt > 0.0:  # what was gathered before the gap or the stop still lands
                    total += flush_pending(hm, last, spray)
            else:
                p0x, p0y, p0z = last[2], last[3], last[4]
                dx = buf_spot[k, 0] - p0x
                dy = buf_spot[k, 1] - p0y
                dzz = buf_spot[k, 2] - p0z
                length = math.sqrt(dx * dx + dy * dy + dzz * dzz)
                n = max(int(math.ceil(length / piece)), 1)
                if n > 1:  # a long move: close what is pending, then split the move
                    total += flush_pending(hm, last, spray)
                for q in range(n):
                    f = (q + 0.5) / n
                    w = dt / n
                    last[8] += w
                    last[9] += length / n
                    last[10] += w * (p0x + dx * f)
                    last[11] += w * (p0y + dy * f)
                    last[12] += w * (p0z + dzz * f)
                    for c in range(3):
                        last[13 + c] += w * (last[5 + c] + (buf_axis[k, c] - last[5 + c]) * f)
                    if n > 1 or last[9] >= piece or last[8] >= max_piece_s:
                        total += flush_pending(hm, last, spray)
        last[0] = 1.0
        last[1] = stamps[k]
        for c in range(3):
            last[2 + c] = buf_spot[k, c]
            last[5 + c] = buf_axis[k, c]
    return total, gaps
