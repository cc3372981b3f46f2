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


@njit(cache=True, nogil=True)
def laser_pass(H, bmax, cell, thickness, zmax, lx, ly, face_tol, origin, dirs, t_min, t_max,
               max_range, t_occ, has_occ, out_t, out_reason, out_points, out_normals):
    """Cast the laser fan from ``origin (3,)`` along ``dirs (n, 3)`` (all in O).

    Fills the hit distance (inf: none), the reason (VALID, NO_SURFACE or LASER_BLOCKED where
    ``has_occ`` and ``t_occ`` is nearer), the lit point (NaN: none) and the solid's outward
    normal there (top surface: bilinear patch normal; below it: the plate face nearest to the
    point; zeros where nothing is hit). Returns the number of VALID rays.
    """
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
def camera_pass(H, bmax, cell, thickness, zmax, camera, lift, reach, hits, normals, out_u_cam,
                out_starts, out_u, out_remaining, out_t):
    """Rays from the lit points ``hits (m, 3)`` (lifted by ``lift`` along ``normals``) to the
    camera at ``camera (3,)``, cast on the height field up to ``reach`` [mm] (at least every
    ray's distance to the camera): fills the unit direction to the camera from the unlifted
    point, the lifted starts, their unit directions and distances to the camera, and the
    distance to the first surface hit (inf: clear)."""
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
def trace_pass(H, bmax, cell, thickness, zmax, lx, ly, face_tol, origin, dirs, t_min, t_max,
               max_range, t_occ, has_occ, camera, lift, camera_reach, occ_T_C_O, occ_r2,
               occ_length, min_intensity, out_t, out_reason, out_cos, out_points):
    """A noise-free scan (or a part of its fan) in one call: :func:`laser_pass`, the cosine of
    incidence, :func:`camera_pass` for the lit points (up to ``camera_reach`` [mm]), their
    camera verdicts (BACK_FACING, CAMERA_SHADOW, CAMERA_BLOCKED by the capped cylinders
    ``occ_T_C_O (k, 4, 4)`` (O into each cylinder's frame), ``occ_r2 (k,)`` [mm^2],
    ``occ_length (k,)`` [mm]) and TOO_DARK below ``min_intensity``, in the order and operations
    of the numpy path."""
    n = dirs.shape[0]
    normals = np.empty((n, 3))
    n_cand = laser_pass(H, bmax, cell, thickness, zmax, lx, ly, face_tol, origin, dirs, t_min,
                        t_max, max_range, t_occ, has_occ, out_t, out_reason, out_points,
                        normals)
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
        camera_pass(H, bmax, cell, thickness, zmax, camera, lift, camera_reach, hits, nrm, u_cam,
                    starts, u, remaining, t_cam)
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
