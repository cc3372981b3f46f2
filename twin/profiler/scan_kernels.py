"""Numba kernels for a whole profiler scan in one call: the scan pose, the noise-free trace
(:func:`twin.profiler.kernels.trace_pass`) and the sensor noise
(:func:`twin.profiler.noise_kernels.measure_pass`).

The pose products are written out term by term (x, y, z, then the translation), in the order
:func:`twin.profiler.numpy_path.scan_pose` uses with whole-array numpy operations, so the two
paths give the same bits without BLAS choosing a summation order.

A profiler's constant inputs travel in one :class:`Scanner` made once per profiler and
occluder set, its noise in a :class:`twin.profiler.noise_kernels.DrawStream` and
:class:`twin.profiler.noise_kernels.SensorModel`, the height field in a
:class:`twin.profiler.kernels.PlateField`. Python hands each bundle to :func:`trace_posed` and
:func:`scan_pass` as a plain tuple of its fields, which the kernels name again first thing:
numba's dispatcher types a plain tuple in C but a named one in Python, about 2 us a bundle and
call (2 % of a scan).

Every ray is traced on its own (the camera rays up to a reach fixed per profiler), so a fan
traced in parts, by :func:`trace_posed` on ray ranges, gives the same bits as in one call.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit

from twin.profiler.kernels import CameraView, Cylinders, LaserFan, PlateField, trace_pass
from twin.profiler.noise_kernels import DrawStream, SensorModel, measure_pass


class Scanner(NamedTuple):
    """A profiler's constant geometry: its fan and camera in S, its pose in B and the
    capped-cylinder occluders (k of them, fixed in B) it is seen past."""

    dirs_S: np.ndarray  # (n, 3) float64 unit laser-ray directions in S
    t_min: np.ndarray  # (n,) float64 [mm] start of the measuring range along each ray
    t_max: np.ndarray  # (n,) float64 [mm] end of the measuring range along each ray
    t_occ: np.ndarray  # (n,) float64 [mm] distance along each ray to the first occluder
    T_B_S: np.ndarray  # (4, 4) float64 the profiler's pose in B [mm]
    camera_S: np.ndarray  # (3,) float64 the camera centre in S [mm]
    T_C_B: np.ndarray  # (k, 4, 4) float64 B into each cylinder's frame C (axis +z_C) [mm]
    occ_r2: np.ndarray  # (k,) float64 each cylinder's squared radius [mm^2]
    occ_length: np.ndarray  # (k,) float64 each cylinder's length along +z_C [mm]
    has_occ: bool  # whether ``t_occ`` applies (k > 0)
    max_range: float  # [mm] longest laser ray
    face_tol: float  # [mm] hits this far below the top surface lie on a plate face
    lift: float  # [mm] camera rays start this far off the surface
    camera_reach: float  # [mm] at least the distance from the camera to any lifted lit point
    min_intensity: float  # cosine of incidence below which a point is TOO_DARK [-]


@njit(cache=True)
def _compose(A, B, out):
    """``out = A @ B`` for (4, 4) rigid transforms, each entry summed k = 0, 1, 2, 3."""
    for i in range(4):
        for j in range(4):
            out[i, j] = ((A[i, 0] * B[0, j] + A[i, 1] * B[1, j]) + A[i, 2] * B[2, j]) \
                + A[i, 3] * B[3, j]


@njit(cache=True)
def scan_pose(scanner, T_B_O, r0, r1, T_O_S, dirs_O, camera_O, T_C_O):
    """Fill ``T_O_S (4, 4)``, the directions ``dirs_O (r1 - r0, 3)`` of fan rays ``r0:r1``, the
    camera centre ``camera_O (3,)`` and each cylinder's ``T_C_O = T_C_B @ T_B_O (k, 4, 4)`` of
    ``scanner`` (:class:`Scanner`) with the plate at ``T_B_O``."""
    T_B_S, rays, camera_S, T_C_B = scanner.T_B_S, scanner.dirs_S, scanner.camera_S, \
        scanner.T_C_B
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
def trace_posed(field, scanner, T_B_O, r0, r1, out_t, out_reason, out_cos, out_points):
    """:func:`scan_pose` then :func:`twin.profiler.kernels.trace_pass` for fan rays ``r0:r1``
    of ``scanner`` (:class:`Scanner`) on ``field``
    (:class:`twin.profiler.kernels.PlateField`) with the plate at ``T_B_O``: fills entries
    ``r0:r1`` of the ``(n,)`` hit distance [mm], reason, cosine of incidence and ``(n, 3)``
    lit point in O [mm]."""
    field, scanner = PlateField(*field), Scanner(*scanner)
    T_O_S = np.empty((4, 4))
    dirs_O = np.empty((r1 - r0, 3))
    camera_O = np.empty(3)
    T_C_O = np.empty((scanner.T_C_B.shape[0], 4, 4))
    scan_pose(scanner, T_B_O, r0, r1, T_O_S, dirs_O, camera_O, T_C_O)
    origin = np.empty(3)
    for i in range(3):
        origin[i] = T_O_S[i, 3]
    fan = LaserFan(origin, dirs_O, scanner.t_min[r0:r1], scanner.t_max[r0:r1],
                   scanner.t_occ[r0:r1], scanner.max_range, scanner.has_occ, scanner.face_tol)
    view = CameraView(camera_O, scanner.lift, scanner.camera_reach)
    cylinders = Cylinders(T_C_O, scanner.occ_r2, scanner.occ_length)
    trace_pass(field, fan, view, cylinders, scanner.min_intensity, out_t[r0:r1],
               out_reason[r0:r1], out_cos[r0:r1], out_points[r0:r1])


@njit(cache=True, nogil=True)
def scan_pass(field, scanner, stream, model, T_B_O, counter, out_xz, out_valid, out_intensity):
    """One profile: :func:`trace_posed`, then the sensor noise of profile ``counter`` of
    ``stream`` under ``model`` (:func:`twin.profiler.noise_kernels.measure_pass`), into
    ``out_xz (n, 2)`` in S [mm], ``out_valid (n,)`` and ``out_intensity (n,) float32``."""
    field, scanner = PlateField(*field), Scanner(*scanner)
    stream, model = DrawStream(*stream), SensorModel(*model)
    n = scanner.dirs_S.shape[0]
    t_hit = np.empty(n)
    reason = np.empty(n, dtype=np.int8)
    cos_inc = np.empty(n)
    points = np.empty((n, 3))
    trace_posed(field, scanner, T_B_O, 0, n, t_hit, reason, cos_inc, points)
    measure_pass(stream, model, counter, t_hit, reason, cos_inc, out_xz, out_valid,
                 out_intensity)
