"""Numba kernels for the stochastic Gaussian spray (see :mod:`twin.world.deposition`).

Randomness comes from a SplitMix64 generator whose 64-bit state lives in a numpy array owned
by the :class:`twin.world.deposition.SprayModel`, so two models never share state and a seed fixes
every packet bit for bit.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit

from dm2.core.tolerances import NEAR_ZERO
from twin.world.heightfield_kernels import bilinear_height, ray_one
from twin.world.splat_kernels import SPLAT_RADIUS_CELLS, splat


class FieldArrays(NamedTuple):
    """A :class:`twin.world.heightfield.HeightField`'s arrays as the kernels take them."""

    H: np.ndarray  # (ny, nx) float64 node heights [mm], updated in place
    bmax: np.ndarray  # (nby, nbx) float64 per-block upper bound of H [mm]
    zmax: np.ndarray  # (1,) float64 upper bound of the whole field [mm]
    dirty: np.ndarray  # (nby, nbx) bool blocks changed since the last mesh
    cell: float  # node spacing [mm]
    thickness: float  # plate thickness [mm]


class Plume(NamedTuple):
    """The parts of the twin's spray that stay fixed over a call."""

    v_packet: float  # volume of one powder packet [mm^3]
    theta_c: float  # critical spray angle [rad]
    normal_cells: int  # half width of the smoothed surface normal [nodes]
    phys: np.ndarray  # PHYS_* entries: efficiency curve, porosity, spray-distance efficiency
    radial: np.ndarray  # radial profile of the plume (:func:`radial_offset`)

_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)


@njit(cache=True)
def next_u64(state):
    state[0] += _GOLDEN
    z = state[0]
    z = (z ^ (z >> np.uint64(30))) * _M1
    z = (z ^ (z >> np.uint64(27))) * _M2
    return z ^ (z >> np.uint64(31))


@njit(cache=True)
def uniform(state):
    """Uniform float in [0, 1)."""
    return float(next_u64(state) >> np.uint64(11)) * (1.0 / 9007199254740992.0)


# the R2 sequence's steps (1/g and 1/g^2 for the plastic number g, the root of x^3 = x + 1): the
# two-dimensional low-discrepancy sequence whose points fill the unit square most evenly
R2_A1 = 0.7548776662466927
R2_A2 = 0.5698402909980532


@njit(cache=True)
def _frac(x):
    return x - math.floor(x)


# the twin's physics beyond the nominal model, packed for the kernels (see
# twin.world.twin_physics.TwinPhysics.kernel_params): curve code, plateau angle [rad], volume
# per dense volume (1 / (1 - porosity)), relative efficiency per mm of spray distance beyond
# the reference standoff, that standoff [mm], the exponent of an extra cos(theta) factor on the
# curve, the logistic curve's steepness [1/rad] and midpoint spray angle [rad]
PHYS_CURVE, PHYS_PLATEAU, PHYS_BULK, PHYS_STANDOFF_SLOPE, PHYS_STANDOFF_REF, PHYS_COS_EXP, \
    PHYS_LOGISTIC_K, PHYS_LOGISTIC_PHI0 = range(8)
CURVE_COS2, CURVE_COS, CURVE_LINEAR, CURVE_PLATEAU, CURVE_LOGISTIC = range(5)


@njit(cache=True)
def efficiency_curve(theta, theta_c, code=CURVE_COS2, theta_p=0.0, k=9.0, phi0=0.61):
    """Relative deposition efficiency at impact angle ``theta`` [rad], 0 from ``theta_c``.

    ``code``: CURVE_COS2 ``cos^2(pi/2 (theta/theta_c)^2)`` (the nominal model), CURVE_COS
    ``cos(theta)``, CURVE_LINEAR ``1 - theta/theta_c``, CURVE_PLATEAU 1 up to ``theta_p``,
    then linear to 0 at ``theta_c``; CURVE_LOGISTIC ``expit(k (phi - phi0))`` in the spray
    angle ``phi = pi/2 - theta`` between jet and surface, 1 at normal impact, with no cut at
    ``theta_c`` (0 from grazing, ``phi <= 0``).
    """
    if code == CURVE_LOGISTIC:
        phi = 0.5 * math.pi - theta
        if phi <= 0.0:
            return 0.0
        return (1.0 + math.exp(-k * (0.5 * math.pi - phi0))) / (1.0 + math.exp(-k * (phi - phi0)))
    if theta >= theta_c:
        return 0.0
    if code == CURVE_COS:
        return math.cos(theta)
    if code == CURVE_LINEAR:
        return 1.0 - theta / theta_c
    if code == CURVE_PLATEAU:
        return 1.0 if theta <= theta_p else (theta_c - theta) / (theta_c - theta_p)
    x = theta / theta_c
    c = math.cos(0.5 * math.pi * x * x)
    return c * c


@njit(cache=True, inline="always")
def radial_offset(u1, radial):
    """Radius across the jet in plume sigmas for ``u1`` in (0, 1]: Box-Muller's Rayleigh radius
    without a table (a Gaussian plume), else the inverse CDF tabulated in ``radial`` (n + 1
    nodes at quantiles k / n), interpolated linearly."""
    if radial.size == 0:
        return math.sqrt(-2.0 * math.log(u1))
    n = radial.size - 1
    f = (1.0 - u1) * n
    k = min(int(f), n - 1)
    w = f - k
    return radial[k] * (1.0 - w) + radial[k + 1] * w


@njit(cache=True, inline="always")
def _axis_slope(h, h0, h1, d0, d1, steepest):
    """Slope along one axis at a node of height ``h`` between ``h0`` (``d0`` [mm] before it)
    and ``h1`` (``d1`` after): the steeper one-sided difference on a crest (anywhere with
    ``steepest``), else the central difference (0 with no span)."""
    if d0 + d1 <= 0.0:
        return 0.0
    if d0 > 0.0 and d1 > 0.0 and (steepest or (h > h0 and h > h1)):
        gl = (h - h0) / d0
        gr = (h1 - h) / d1
        return gl if abs(gl) > abs(gr) else gr
    return (h1 - h0) / (d0 + d1)


@njit(cache=True)
def _robust_gradient(H, cell, x, y, k, steepest=False):
    """Surface gradient ``(gx, gy)`` at ``(x, y)`` over +-k cells, robust to narrow features.

    Along each axis the two one-sided differences over ``k`` cells are taken. Where the node
    stands above both ends (a crest along that axis) the steeper one is kept: a spike or ridge
    narrower than the stencil, whose central difference reads flat, shows the slope of its
    flanks, so it cannot keep full efficiency and capture the packets aimed around it.
    Elsewhere (a face, a trough) it is the central difference: a pit reads as flat and fills,
    so the roughness at the packets' scale stays damped (a trough read as steep would lose
    efficiency and deepen without bound). ``steepest`` keeps the steeper one-sided difference
    everywhere."""
    ny, nx = H.shape
    i = min(max(int(x / cell), 0), nx - 1)
    j = min(max(int(y / cell), 0), ny - 1)
    i0 = max(i - k, 0)
    i1 = min(i + k, nx - 1)
    j0 = max(j - k, 0)
    j1 = min(j + k, ny - 1)
    h = H[j, i]
    gx = _axis_slope(h, H[j, i0], H[j, i1], (i - i0) * cell, (i1 - i) * cell, steepest)
    gy = _axis_slope(h, H[j0, i], H[j1, i], (j - j0) * cell, (j1 - j) * cell, steepest)
    return gx, gy


@njit(cache=True)
def _smoothed_normal(H, cell, x, y, k):
    """Upward unit normal at ``(x, y)`` from :func:`_robust_gradient` over +-k cells."""
    gx, gy = _robust_gradient(H, cell, x, y, k)
    n = math.sqrt(gx * gx + gy * gy + 1.0)
    return -gx / n, -gy / n, 1.0 / n


@njit(cache=True, nogil=True)
def spray_step(field, state, seq, lam, spot, axis, sigma, back_mm, zeta0, plume):
    """Send ``lam`` packets (on average) from the plume at ``spot`` along ``axis`` onto ``field``
    (:class:`FieldArrays`).

    The count is ``lam`` rounded down or up at random, so that it is ``lam`` on average; each
    packet's place across the jet is the next point of the R2 sequence ``seq`` (float64 (2,),
    advanced in place), carried from step to step, so that the packets cover the plume as
    evenly as the millions of particles of a real powder jet do (see
    :mod:`twin.world.deposition`).

    ``plume`` (:class:`Plume`) carries the twin's own physics: efficiency curve, porosity,
    spray-distance efficiency and the plume's profile; ``sigma`` [mm], ``back_mm`` (the nozzle
    exit behind ``spot``) and ``zeta0`` (efficiency at normal incidence) are this step's.

    Returns
    -------
    (deposited volume [mm^3], packets drawn, packets that missed the plate)
    """
    H, bmax, zmax, dirty = field.H, field.bmax, field.zmax, field.dirty
    cell, thickness = field.cell, field.thickness
    v_packet, theta_c, normal_cells = plume.v_packet, plume.theta_c, plume.normal_cells
    phys, radial = plume.phys, plume.radial
    ax = axis[0]
    ay = axis[1]
    az = axis[2]
    an = math.sqrt(ax * ax + ay * ay + az * az)
    ax /= an
    ay /= an
    az /= an
    # orthonormal basis (e1, e2) of the plane across the jet
    if abs(az) < 0.9:
        e1x, e1y, e1z = ay, -ax, 0.0
    else:
        e1x, e1y, e1z = 0.0, az, -ay
    n1 = math.sqrt(e1x * e1x + e1y * e1y + e1z * e1z)
    e1x /= n1
    e1y /= n1
    e1z /= n1
    e2x = ay * e1z - az * e1y
    e2y = az * e1x - ax * e1z
    e2z = ax * e1y - ay * e1x
    vertical = abs(ax) < NEAR_ZERO and abs(ay) < NEAR_ZERO and az < 0.0
    code = int(phys[PHYS_CURVE])
    theta_p = phys[PHYS_PLATEAU]
    bulk = phys[PHYS_BULK]
    slope = phys[PHYS_STANDOFF_SLOPE]
    s_ref = phys[PHYS_STANDOFF_REF]
    cos_exp = phys[PHYS_COS_EXP]
    k_logistic = phys[PHYS_LOGISTIC_K]
    phi0 = phys[PHYS_LOGISTIC_PHI0]
    n_packets = int(lam + uniform(state))
    w = np.empty((2 * SPLAT_RADIUS_CELLS + 1) ** 2)
    deposited = 0.0
    missed = 0
    for _ in range(n_packets):
        seq[0] = _frac(seq[0] + R2_A1)
        seq[1] = _frac(seq[1] + R2_A2)
        u1 = 1.0 - seq[0]
        u2 = seq[1]
        r = sigma * radial_offset(u1, radial)
        g1 = r * math.cos(2.0 * math.pi * u2)
        g2 = r * math.sin(2.0 * math.pi * u2)
        ox = spot[0] + g1 * e1x + g2 * e2x - back_mm * ax
        oy = spot[1] + g1 * e1y + g2 * e2y - back_mm * ay
        oz = spot[2] + g1 * e1z + g2 * e2z - back_mm * az
        if vertical:  # straight down: the hit is the surface height under the packet
            hz = bilinear_height(H, cell, ox, oy)
            t = oz - hz if hz == hz else np.inf
        else:
            t = ray_one(H, bmax, cell, thickness, zmax[0], ox, oy, oz, ax, ay, az, np.inf)
        if not t < np.inf:
            missed += 1
            continue
        hx = ox + t * ax
        hy = oy + t * ay
        nx_, ny_, nz_ = _smoothed_normal(H, cell, hx, hy, normal_cells)
        cos_t = -(ax * nx_ + ay * ny_ + az * nz_)
        if cos_t <= 0.0:
            continue
        theta = math.acos(min(cos_t, 1.0))
        zeta = zeta0 * efficiency_curve(theta, theta_c, code, theta_p, k_logistic, phi0)
        if cos_exp != 0.0:
            zeta *= min(cos_t, 1.0) ** cos_exp
        if slope != 0.0:  # the nozzle exit lies t from the hit
            zeta *= max(1.0 + slope * (t - s_ref), 0.0)
        vol = v_packet * min(zeta, 1.0)
        if bulk != 1.0:  # pores: the stuck mass stands taller than at full density
            vol *= bulk
        if vol > 0.0:
            splat(H, bmax, zmax, dirty, cell, hx, hy, vol, w)
            deposited += vol
    return deposited, n_packets, missed


@njit(cache=True, nogil=True)
def spray_samples(field, state, seq, lam, spots, axes, sigma, back_mm, zeta0, plume, out_vol,
                  out_counts):
    """:func:`spray_step` for each executed-motion sample ``k`` (``lam[k] == 0`` skips it)."""
    for k in range(spots.shape[0]):
        if lam[k] <= 0.0:
            out_vol[k] = 0.0
            continue
        vol, n, missed = spray_step(field, state, seq, lam[k], spots[k], axes[k], sigma[k],
                                    back_mm[k], zeta0[k], plume)
        out_vol[k] = vol
        out_counts[0] += n
        out_counts[1] += missed
