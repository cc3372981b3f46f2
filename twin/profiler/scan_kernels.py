"""Numba kernels for a whole profiler scan in one call: the scan pose, the noise-free trace
(:func:`twin.profiler.kernels.trace_pass`) and the sensor noise
(:func:`twin.profiler.noise_kernels.measure_pass`).

The pose products are written out term by term (x, y, z, then the translation), in the order
:func:`twin.profiler.numpy_path.scan_pose` uses with whole-array numpy operations, so the two
paths give the same bits without BLAS choosing a summation order.

A profiler's constant inputs travel in two arrays made once per profiler:

- ``rays (n, 6)``: the fan's unit directions in S (x, y, z), ``t_min``, ``t_max`` [mm] of the
  measuring range along each ray, the distance to the first occluder [mm] (inf: none);
- ``params (N_PARAMS,)``: see the ``P_*`` indices below.

Every ray is traced on its own (the camera rays up to a reach fixed per profiler), so a fan
traced in parts, by :func:`trace_posed` on ray ranges, gives the same bits as in one call.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from twin.profiler.kernels import trace_pass
from twin.profiler.noise_kernels import measure_pass

P_FACE_TOL = 0  # [mm] hits this far below the top surface lie on a plate face
P_LIFT = 1  # [mm] camera rays start this far off the surface
P_MIN_INTENSITY = 2
P_MAX_RANGE = 3  # [mm] longest laser ray
P_RANGE_SIGMA = 4  # [mm]
P_SPECKLE_SIGMA = 5  # [mm]
P_OUTLIER_PROB = 6
P_DROPOUT_PROB = 7
P_Z_START = 8  # [mm]
P_Z_END = 9  # [mm]
P_GHOST_LO = 10  # [mm]
P_GHOST_HI = 11  # [mm]
P_HAS_OCC = 12  # 1.0 where the laser occluder distances apply
P_CAMERA_REACH = 13  # [mm] at least the distance from the camera to any lifted lit point
N_PARAMS = 14


@njit(cache=True)
def _compose(A, B, out):
    """``out = A @ B`` for (4, 4) rigid transforms, each entry summed k = 0, 1, 2, 3."""
    for i in range(4):
        for j in range(4):
            out[i, j] = ((A[i, 0] * B[0, j] + A[i, 1] * B[1, j]) + A[i, 2] * B[2, j]) \
                + A[i, 3] * B[3, j]


@njit(cache=True)
def scan_pose(T_B_O, T_B_S, rays, camera_S, T_C_B, r0, r1, T_O_S, dirs_O, camera_O, T_C_O):
    """Fill ``T_O_S (4, 4)``, the directions ``dirs_O (r1 - r0, 3)`` of fan rays ``r0:r1``, the
    camera centre ``camera_O (3,)`` and each cylinder's ``T_C_O = T_C_B @ T_B_O (k, 4, 4)``."""
    T_O_B = np.zeros((4, 4))
    for i in range(3):
        for j in range(3):
            T_O_B[i, j] = T_B_O[j, i]
        T_O_B[i, 3] = -((T_B_O[0, i] * T_B_O[0, 3] + T_B_O[1, i] * T_B_O[1, 3])
                        + T_B_O[2, i] * T_B_O[2, 3])
    T_O_B[3, 3] = 1.0
    _compose(T_O_B, T_B_S, T_O_S)
    for k in range(r0, r1):
        for i in range(3):
            dirs_O[k - r0, i] = (rays[k, 0] * T_O_S[i, 0] + rays[k, 1] * T_O_S[i, 1]) \
                + rays[k, 2] * T_O_S[i, 2]
    for i in range(3):
        camera_O[i] = ((T_O_S[i, 0] * camera_S[0] + T_O_S[i, 1] * camera_S[1])
                       + T_O_S[i, 2] * camera_S[2]) + T_O_S[i, 3]
    for o in range(T_C_B.shape[0]):
        _compose(T_C_B[o], T_B_O, T_C_O[o])


@njit(cache=True, nogil=True)
def trace_posed(H, bmax, zmax, cell, thickness, lx, ly, T_B_O, T_B_S, rays, camera_S, T_C_B,
                cylinders, params, r0, r1, out_t, out_reason, out_cos, out_points):
    """:func:`scan_pose` then :func:`twin.profiler.kernels.trace_pass` for fan rays ``r0:r1``
    (their entries of the ``(n,)`` / ``(n, 3)`` outputs) on the height field ``H`` with block
    bounds ``bmax`` and top ``zmax (1,)``; capped cylinders ``cylinders (k, 2)`` hold the
    squared radius [mm^2] and the length [mm]."""
    T_O_S = np.empty((4, 4))
    dirs_O = np.empty((r1 - r0, 3))
    camera_O = np.empty(3)
    T_C_O = np.empty((T_C_B.shape[0], 4, 4))
    scan_pose(T_B_O, T_B_S, rays, camera_S, T_C_B, r0, r1, T_O_S, dirs_O, camera_O, T_C_O)
    origin = np.empty(3)
    for i in range(3):
        origin[i] = T_O_S[i, 3]
    trace_pass(H, bmax, cell, thickness, zmax[0], lx, ly, params[P_FACE_TOL], origin, dirs_O,
               rays[r0:r1, 3], rays[r0:r1, 4], params[P_MAX_RANGE], rays[r0:r1, 5],
               params[P_HAS_OCC] != 0.0, camera_O, params[P_LIFT], params[P_CAMERA_REACH],
               T_C_O, cylinders[:, 0], cylinders[:, 1], params[P_MIN_INTENSITY],
               out_t[r0:r1], out_reason[r0:r1], out_cos[r0:r1], out_points[r0:r1])


@njit(cache=True, nogil=True)
def scan_pass(H, bmax, zmax, cell, thickness, lx, ly, T_B_O, T_B_S, rays, camera_S, T_C_B,
              cylinders, params, seed, sensor, counter, speckle_kernel, out_xz, out_valid,
              out_intensity):
    """One profile: :func:`trace_posed`, then the sensor noise of profile ``counter`` of
    ``sensor`` under ``seed`` (:func:`twin.profiler.noise_kernels.measure_pass`)."""
    n = rays.shape[0]
    t_hit = np.empty(n)
    reason = np.empty(n, dtype=np.int8)
    cos_inc = np.empty(n)
    points = np.empty((n, 3))
    trace_posed(H, bmax, zmax, cell, thickness, lx, ly, T_B_O, T_B_S, rays, camera_S, T_C_B,
                cylinders, params, 0, n, t_hit, reason, cos_inc, points)
    measure_pass(seed, sensor, counter, speckle_kernel, params[P_GHOST_LO], params[P_GHOST_HI],
                 t_hit, reason, cos_inc, params[P_RANGE_SIGMA], params[P_SPECKLE_SIGMA],
                 params[P_OUTLIER_PROB], params[P_DROPOUT_PROB], rays[:, 0], rays[:, 2],
                 params[P_Z_START], params[P_Z_END], out_xz, out_valid, out_intensity)
