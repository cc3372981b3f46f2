"""Numba kernels for :class:`twin.profiler.sensor.VirtualProfiler`'s geometry: one pass per
scan stage (the sensor noise is in :mod:`twin.profiler.noise_kernels`).

They do, ray by ray and in the same floating-point operations, what the profiler's numpy path
(:meth:`twin.profiler.sensor.VirtualProfiler.trace_numpy`) does with whole-array
operations, so both give the same bits: the numpy path writes its small dot and matrix
products out term by term (x, y, z) rather than leave the summation order to ``einsum`` or
BLAS.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit

from dm2.core.tolerances import FACING_COS
from twin.profiler.occluders import cylinder_blocks_one as _cylinder_blocks_one
from twin.world.heightfield_kernels import bilinear_height, normal_at, ray_one

# Reason codes, as in twin.profiler.sensor.
VALID = 0
NO_SURFACE = 1
LASER_BLOCKED = 2
CAMERA_SHADOW = 3
CAMERA_BLOCKED = 4
BACK_FACING = 5
TOO_DARK = 6


class PlateField(NamedTuple):
    """The plate-and-deposit solid the fan is cast on: a
    :class:`twin.world.heightfield.HeightField`'s arrays and the plate around them, all in O
    (z_O = 0 is the bare plate's top, the plate spans ``[0, lx] x [0, ly] x [-thickness, 0]``).
    """

    H: np.ndarray  # (ny, nx) float64 node heights z_O [mm]
    bmax: np.ndarray  # (nby, nbx) float64 per-block upper bound of H [mm]
    zmax: np.ndarray  # (1,) float64 upper bound of the whole field [mm]
    cell: float  # node spacing [mm]
    thickness: float  # plate thickness [mm]
    lx: float  # plate size along x_O [mm]
    ly: float  # plate size along y_O [mm]


class LaserFan(NamedTuple):
    """The laser rays of one pass, in O."""

    origin: np.ndarray  # (3,) float64 the laser's origin (the S origin) in O [mm]
    dirs: np.ndarray  # (n, 3) float64 unit ray directions in O
    t_min: np.ndarray  # (n,) float64 [mm] start of the measuring range along each ray
    t_max: np.ndarray  # (n,) float64 [mm] end of the measuring range along each ray
    t_occ: np.ndarray  # (n,) float64 [mm] distance to the first occluder (inf: none)
    max_range: float  # [mm] longest ray cast on the field
    has_occ: bool  # whether ``t_occ`` applies (an occluder set is given)
    face_tol: float  # [mm] hits this far below the top surface lie on a plate face


class CameraView(NamedTuple):
    """The triangulation camera of one pass, in O."""

    centre: np.ndarray  # (3,) float64 the camera centre in O [mm]
    lift: float  # [mm] camera rays start this far off the surface, along its normal
    reach: float  # [mm] at least the distance from the camera to any lifted lit point


class Cylinders(NamedTuple):
    """Capped-cylinder occluders of the camera rays (k of them; k = 0: none)."""

    T_C_O: np.ndarray  # (k, 4, 4) float64 O into each cylinder's frame C (axis +z_C) [mm]
    r2: np.ndarray  # (k,) float64 squared radius [mm^2]
    length: np.ndarray  # (k,) float64 length along +z_C [mm]


@njit(cache=True, nogil=True)
def laser_pass(field, fan, out_t, out_reason, out_points, out_normals):
    """Cast the laser fan ``fan`` (:class:`LaserFan`) on ``field`` (:class:`PlateField`).

    Fills the ``(n,)`` hit distance [mm] (inf: none), the reason (VALID, NO_SURFACE or
    LASER_BLOCKED where ``fan.has_occ`` and ``fan.t_occ`` is nearer), the ``(n, 3)`` lit point
    in O [mm] (NaN: none) and the solid's outward normal there (top surface: bilinear patch
    normal; below it: the plate face nearest to the point; zeros where nothing is hit).
    Returns the number of VALID rays.
    """
    H, bmax, cell, thickness, zmax = field.H, field.bmax, field.cell, field.thickness, \
        field.zmax[0]
    lx, ly, face_tol = field.lx, field.ly, fan.face_tol
    origin, dirs, t_min, t_max, t_occ = fan.origin, fan.dirs, fan.t_min, fan.t_max, fan.t_occ
    max_range, has_occ = fan.max_range, fan.has_occ
    n = dirs.shape[0]
    n_valid = 0
    for k in range(n):
        dx, dy, dz = dirs[k, 0], dirs[k, 1], dirs[k, 2]
        t = ray_one(H, bmax, cell, thickness, zmax, origin[0], origin[1], origin[2],
                    dx, dy, dz, max_range)
        out_t[k] = t
        reason = NO_SURFACE
        if t < np.inf and t >= t_min[k] and t <= t_max[k]:
            reason = VALID
        if t < np.inf:
            px = origin[0] + t * dx
            py = origin[1] + t * dy
            pz = origin[2] + t * dz
            out_points[k, 0] = px
            out_points[k, 1] = py
            out_points[k, 2] = pz
            top = bilinear_height(H, cell, px, py)
            if pz >= top - face_tol:
                nx_, ny_, nz_ = normal_at(H, cell, px, py)
                out_normals[k, 0] = nx_
                out_normals[k, 1] = ny_
                out_normals[k, 2] = nz_
            else:  # on a side face or the bottom of the plate (NaN height: just off it)
                best = abs(px)
                face = 0
                g = abs(lx - px)
                if g < best:
                    best, face = g, 1
                g = abs(py)
                if g < best:
                    best, face = g, 2
                g = abs(ly - py)
                if g < best:
                    best, face = g, 3
                g = abs(pz + thickness)
                if g < best:
                    best, face = g, 4
                out_normals[k, 0] = 0.0
                out_normals[k, 1] = 0.0
                out_normals[k, 2] = 0.0
                if face == 0:
                    out_normals[k, 0] = -1.0
                elif face == 1:
                    out_normals[k, 0] = 1.0
                elif face == 2:
                    out_normals[k, 1] = -1.0
                elif face == 3:
                    out_normals[k, 1] = 1.0
                else:
                    out_normals[k, 2] = -1.0
        else:
            for c in range(3):
                out_points[k, c] = np.nan
                out_normals[k, c] = 0.0
        if reason == VALID and has_occ and t_occ[k] < t:
            reason = LASER_BLOCKED
        out_reason[k] = reason
        if reason == VALID:
            n_valid += 1
    return n_valid


@njit(cache=True, nogil=True)
def camera_pass(field, view, hits, normals, out_u_cam, out_starts, out_u, out_remaining, out_t):
    """Rays from the lit points ``hits (m, 3)`` in O (lifted by ``view.lift`` along
    ``normals``) to the camera at ``view.centre`` (:class:`CameraView`), cast on ``field``
    (:class:`PlateField`) up to ``view.reach`` [mm] (at least every ray's distance to the
    camera): fills the unit direction to the camera from the unlifted point, the lifted starts
    [mm], their unit directions and distances to the camera [mm], and the distance to the
    first surface hit [mm] (inf: clear)."""
    H, bmax, cell, thickness, zmax = field.H, field.bmax, field.cell, field.thickness, \
        field.zmax[0]
    camera, lift, reach = view.centre, view.lift, view.reach
    m = hits.shape[0]
    for k in range(m):
        a0 = camera[0] - hits[k, 0]
        a1 = camera[1] - hits[k, 1]
        a2 = camera[2] - hits[k, 2]
        dist = math.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
        out_u_cam[k, 0] = a0 / dist
        out_u_cam[k, 1] = a1 / dist
        out_u_cam[k, 2] = a2 / dist
        s0 = hits[k, 0] + lift * normals[k, 0]
        s1 = hits[k, 1] + lift * normals[k, 1]
        s2 = hits[k, 2] + lift * normals[k, 2]
        out_starts[k, 0] = s0
        out_starts[k, 1] = s1
        out_starts[k, 2] = s2
        b0 = camera[0] - s0
        b1 = camera[1] - s1
        b2 = camera[2] - s2
        rem = math.sqrt(b0 * b0 + b1 * b1 + b2 * b2)
        out_remaining[k] = rem
        out_u[k, 0] = b0 / rem
        out_u[k, 1] = b1 / rem
        out_u[k, 2] = b2 / rem
        out_t[k] = ray_one(H, bmax, cell, thickness, zmax, s0, s1, s2, out_u[k, 0],
                           out_u[k, 1], out_u[k, 2], reach)


@njit(cache=True, nogil=True)
def trace_pass(field, fan, view, cylinders, min_intensity, out_t, out_reason, out_cos,
               out_points):
    """A noise-free scan (or a part of its fan) in one call: :func:`laser_pass`, the cosine of
    incidence, :func:`camera_pass` for the lit points, their camera verdicts (BACK_FACING,
    CAMERA_SHADOW, CAMERA_BLOCKED by ``cylinders``, a :class:`Cylinders`) and TOO_DARK below
    the cosine ``min_intensity``, in the order and operations of the numpy path. Fills the
    ``(n,)`` hit distance [mm], reason, cosine of incidence and ``(n, 3)`` lit point in O [mm]."""
    dirs = fan.dirs
    occ_T_C_O, occ_r2, occ_length = cylinders.T_C_O, cylinders.r2, cylinders.length
    n = dirs.shape[0]
    normals = np.empty((n, 3))
    n_cand = laser_pass(field, fan, out_t, out_reason, out_points, normals)
    for k in range(n):
        c = -(normals[k, 0] * dirs[k, 0] + normals[k, 1] * dirs[k, 1]
              + normals[k, 2] * dirs[k, 2])
        out_cos[k] = min(max(c, 0.0), 1.0)
    if n_cand:
        cand = np.empty(n_cand, dtype=np.int64)
        m = 0
        for k in range(n):
            if out_reason[k] == VALID:
                cand[m] = k
                m += 1
        hits = np.empty((m, 3))
        nrm = np.empty((m, 3))
        for q in range(m):
            for c in range(3):
                hits[q, c] = out_points[cand[q], c]
                nrm[q, c] = normals[cand[q], c]
        u_cam, starts = np.empty((m, 3)), np.empty((m, 3))
        u, remaining, t_cam = np.empty((m, 3)), np.empty(m), np.empty(m)
        camera_pass(field, view, hits, nrm, u_cam, starts, u, remaining, t_cam)
        for q in range(m):
            facing = (nrm[q, 0] * u_cam[q, 0] + nrm[q, 1] * u_cam[q, 1]
                      + nrm[q, 2] * u_cam[q, 2]) > FACING_COS
            why = VALID
            if not facing:
                why = BACK_FACING
            elif t_cam[q] < remaining[q]:
                why = CAMERA_SHADOW
            if why == VALID:
                for o in range(occ_r2.shape[0]):
                    if _cylinder_blocks_one(occ_T_C_O[o], occ_r2[o], occ_length[o], starts[q],
                                            u[q], remaining[q]):
                        why = CAMERA_BLOCKED
                        break
            out_reason[cand[q]] = why
    for k in range(n):
        if out_reason[k] == VALID and out_cos[k] < min_intensity:
            out_reason[k] = TOO_DARK
