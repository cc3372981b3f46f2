"""Where a tilted spray's footprint can lie on the reference's height map
(:func:`dm2.reference.kernels.deposit_spot`).

A tilted spray at the top of a tall wall reaches down to the plate: the rays that pass the
wall's edge land ``height * tan(tilt)`` farther out. The square that holds every such ray is
tens of millimetres wide, most of it far from any ray. The kernel visits, row by row, only the
band along the tilt that can hold the footprint (:func:`row_span`), with the same arithmetic
per visited cell: the deposit is the same, bit for bit, as over the whole square. The band
holds while every height lies in ``[0, zmax]``, the map's highest value that the model keeps
(``NearNetReference.heights_written`` after writing the map from outside).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

NO_BAND = (0.0, 0.0, 0.0, 0.0, 0.0)  # a vertical spray's band: not used


@njit(cache=True)
def tilted_band(px, py, pz, ax, ay, az, zmax, radius):
    """Where a tilted spray's footprint can be, as ``(e_x, e_y, s_lo, s_hi, half_width)``.

    A cell of height ``z`` at horizontal offset ``r`` from the impact point ``p`` is in the
    footprint when its surface point lies within ``radius`` of the axis (unit ``a``, tilted
    along the horizontal unit ``e``, ``c = |a_xy|``, ``A = |a_z|``). Its distance from the axis
    has two orthogonal parts: ``w = r . (-e_y, e_x)`` across the tilt and ``s A + (z - p_z) c``
    in the tilt's vertical plane (``s = r . e``). With every height in ``[0, zmax]``, a cell in
    the footprint has ``|w| <= radius`` and ``s`` in ``[s_lo, s_hi]``: a band along the tilt,
    much narrower than the square that holds it on a tall part (rays passing a wall's top
    reach down to the plate)."""
    c = math.sqrt(ax * ax + ay * ay)
    a_abs = abs(az)
    s_lo = (-radius - (zmax - pz) * c) / a_abs
    s_hi = (radius + pz * c) / a_abs
    return (ax / c, ay / c, s_lo, s_hi, radius)


@njit(cache=True)
def row_span(band, ry, px, cell, i_lo, i_hi):
    """The columns ``[ia, ib]`` (within ``[i_lo, i_hi]``; empty when ``ia > ib``) of the row at
    ``ry`` from the impact point that can hold the tilted footprint :func:`tilted_band`,
    widened by a cell on each side so that no rounding drops a cell the footprint reaches."""
    e_x, e_y, s_lo, s_hi, half = band
    rx_lo = -np.inf
    rx_hi = np.inf
    if e_x != 0.0:  # s = rx e_x + ry e_y in [s_lo, s_hi]
        a = (s_lo - ry * e_y) / e_x
        b = (s_hi - ry * e_y) / e_x
        rx_lo, rx_hi = min(a, b), max(a, b)
    elif not s_lo <= ry * e_y <= s_hi:
        return i_lo, i_lo - 1
    if e_y != 0.0:  # w = -rx e_y + ry e_x in [-half, half]
        a = (ry * e_x - half) / e_y
        b = (ry * e_x + half) / e_y
        rx_lo, rx_hi = max(rx_lo, min(a, b)), min(rx_hi, max(a, b))
    elif not -half <= ry * e_x <= half:
        return i_lo, i_lo - 1
    if rx_lo > rx_hi:
        return i_lo, i_lo - 1
    fa = math.floor((px + rx_lo) / cell - 0.5) - 1.0  # clamped as floats: a nearly axis-
    fb = math.ceil((px + rx_hi) / cell - 0.5) + 1.0  # parallel tilt gives huge bounds
    return (i_lo if fa < i_lo else int(fa)), (i_hi if fb > i_hi else int(fb))
