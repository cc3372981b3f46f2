"""The virtual profiler's numpy path: whole-array operations, one stage at a time.

:meth:`twin.profiler.sensor.VirtualProfiler.trace` and ``measure`` run the numba kernels of
:mod:`twin.profiler.kernels`; these functions are the same model written plainly (and cast on
any surface object with ``raycast``, ``normals_at``, ``height_at``, ``size_mm`` and
``thickness_mm``, or with ``raycast`` and ``solid_normals_at``). The two give the same
bits, which the tests check.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from dm2.core.messages import Profile
from dm2.core.tolerances import FACING_COS
from twin.profiler.model import (
    _FACE_TOL_MM,
    _LIFT_MM,
    BACK_FACING,
    CAMERA_BLOCKED,
    CAMERA_SHADOW,
    DROPOUT,
    LASER_BLOCKED,
    NO_SURFACE,
    TOO_DARK,
    VALID,
    ProfileTrace,
    first_occluder_hit,
)


def trace_numpy(prof, hf, T_B_O: np.ndarray,
                    occluders: Sequence | None = None) -> ProfileTrace:
    """``prof.trace`` in whole-array numpy operations on any surface object with
    ``raycast``, ``normals_at``, ``height_at``, ``size_mm`` and ``thickness_mm``."""
    occluders = tuple(occluders or ())
    n = prof.dirs_S.shape[0]
    T_O_S, dirs_O, camera_O = scan_pose(prof, T_B_O)
    o_O = T_O_S[:3, 3]
    origins_O = np.broadcast_to(o_O, (n, 3)).copy()
    t_hit = np.asarray(hf.raycast(origins_O, dirs_O, max_range_mm=float(prof._t_max.max())),
                       dtype=np.float64)
    in_range = np.isfinite(t_hit) & (t_hit >= prof._t_min) & (t_hit <= prof._t_max)
    reason = np.where(in_range, VALID, NO_SURFACE).astype(np.int8)

    points_O = np.full((n, 3), np.nan)
    hit = np.isfinite(t_hit)
    points_O[hit] = o_O + t_hit[hit, None] * dirs_O[hit]
    normals_O = np.zeros((n, 3))
    normals_O[hit] = _solid_normals(hf, points_O[hit])
    cos_inc = np.clip(-_dot_rows(normals_O, dirs_O), 0.0, 1.0)

    if occluders:
        reason[(reason == VALID) & (prof._laser_occluder_t(occluders) < t_hit)] = \
            LASER_BLOCKED

    cand = np.flatnonzero(reason == VALID)
    if cand.size:
        reason[cand] = _camera_visibility(hf, T_B_O, camera_O, prof._camera_reach_mm,
                                          points_O[cand], normals_O[cand], occluders)
    dark = (reason == VALID) & (cos_inc < prof.noise.min_intensity)
    reason[dark] = TOO_DARK
    return ProfileTrace(t_hit, reason, cos_inc, points_O)


def scan_pose(prof, T_B_O: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``T_O_S (4, 4)``, the fan's unit directions ``dirs_O (n, 3)`` and the camera centre
    ``camera_O (3,)`` of ``prof`` with the plate at ``T_B_O``, every product summed term by
    term (x, y, z, then the translation) like :func:`twin.profiler.scan_kernels.scan_pose`."""
    T_B_O = np.asarray(T_B_O, dtype=np.float64)
    if T_B_O.shape != (4, 4) or not np.all(np.isfinite(T_B_O)):
        raise ValueError(f"scan_pose: T_B_O must be a finite (4, 4) pose, got {T_B_O.shape}")
    Rt, t = T_B_O[:3, :3].T, T_B_O[:3, 3]
    T_O_B = np.zeros((4, 4))
    T_O_B[:3, :3] = Rt
    T_O_B[:3, 3] = -((Rt[:, 0] * t[0] + Rt[:, 1] * t[1]) + Rt[:, 2] * t[2])
    T_O_B[3, 3] = 1.0
    A, B = T_O_B, prof.T_B_S
    T_O_S = ((A[:, 0:1] * B[0] + A[:, 1:2] * B[1]) + A[:, 2:3] * B[2]) + A[:, 3:4] * B[3]
    R, d, c = T_O_S[:3, :3], prof.dirs_S, prof.camera_S
    dirs_O = (d[:, 0:1] * R[:, 0] + d[:, 1:2] * R[:, 1]) + d[:, 2:3] * R[:, 2]
    camera_O = ((R[:, 0] * c[0] + R[:, 1] * c[1]) + R[:, 2] * c[2]) + T_O_S[:3, 3]
    return T_O_S, dirs_O, camera_O


def _camera_visibility(hf, T_B_O, camera_O, camera_reach_mm, hits_O, normals_O,
                       occluders) -> np.ndarray:
    """Reason codes (VALID or a camera failure) for lit points ``hits_O (m, 3)`` seen from the
    camera centre ``camera_O (3,)``, camera rays cast up to ``camera_reach_mm``."""
    to_cam = camera_O - hits_O
    dist = np.linalg.norm(to_cam, axis=1)
    u = to_cam / dist[:, None]
    out = np.full(hits_O.shape[0], VALID, dtype=np.int8)
    facing = _dot_rows(normals_O, u) > FACING_COS
    out[~facing] = BACK_FACING
    starts = hits_O + _LIFT_MM * normals_O
    remaining = np.linalg.norm(camera_O - starts, axis=1)
    u = (camera_O - starts) / remaining[:, None]
    t_hf = np.asarray(hf.raycast(starts, u, max_range_mm=camera_reach_mm), dtype=np.float64)
    shadow = t_hf < remaining
    out[facing & shadow] = CAMERA_SHADOW
    if occluders:
        starts_B = starts @ T_B_O[:3, :3].T + T_B_O[:3, 3]
        u_B = u @ T_B_O[:3, :3].T
        blocked = first_occluder_hit(occluders, starts_B, u_B) < remaining
        out[(out == VALID) & blocked] = CAMERA_BLOCKED
    return out


def measure_numpy(prof, trace: ProfileTrace, stamp_s: float, counter: int,
                  spray: float = 1.0) -> Profile:
    """``prof.measure`` in whole-array numpy operations (the artefacts of
    :mod:`twin.profiler.artefacts` are numpy already: the same call)."""
    counter = int(counter)
    noisy_range, reason, intensity = _noise(prof, trace, counter)
    z = noisy_range * prof.dirs_S[:, 2]
    reason[(reason == VALID) & ((z < prof.sensors.z_start_mm)
                                | (z > prof.sensors.z_end_mm))] = NO_SURFACE
    valid = reason == VALID
    xz = np.full((reason.size, 2), np.nan)
    xz[valid, 0] = noisy_range[valid] * prof.dirs_S[valid, 0]
    xz[valid, 1] = z[valid]
    intensity = np.where(valid, intensity, 0.0).astype(np.float32)
    if prof._artefacts is not None:
        prof._artefacts.apply(xz, valid, intensity, float(stamp_s), counter, spray)
    return Profile(prof.sensor_id, stamp_s, counter, xz, valid, intensity)

def _noise(prof, trace: ProfileTrace, counter: int):
    """Noisy ranges, reasons and intensities; every draw is made whatever the settings."""
    nz = prof.noise
    n = trace.range_mm.size
    gauss, speckle, u_drop, u_ghost, ghost_mm = prof._draws(counter, n)
    reason = trace.reason.copy()
    rng_mm = trace.range_mm + nz.range_sigma_mm * gauss + nz.speckle_sigma_mm * speckle
    ghost = (reason == VALID) & (u_ghost < nz.outlier_prob)
    rng_mm = np.where(ghost, rng_mm + ghost_mm, rng_mm)
    intensity = np.where(ghost, 0.5 * trace.cos_incidence, trace.cos_incidence)
    reason[(reason == VALID) & (u_drop < nz.dropout_prob)] = DROPOUT
    return rng_mm, reason, intensity



def _dot_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise dot products ``(m,)`` of ``(m, 3)`` arrays, summed x, y, then z (the kernels'
    order; ``einsum`` may pick another at run time)."""
    return a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1] + a[:, 2] * b[:, 2]


def _solid_normals(hf, points_O: np.ndarray) -> np.ndarray:
    """Outward unit normals ``(m, 3)`` of the plate-and-deposit solid at surface points.

    Points on the top surface take the exact bilinear-patch normal; points below it lie on
    the plate's side faces or bottom and take that face's normal. A surface that is not a
    height field (undercuts, e.g. :mod:`twin.profiler.artifact_surface`) gives its normals
    itself through ``solid_normals_at(points_O)``.
    """
    if points_O.shape[0] == 0:
        return np.zeros((0, 3))
    if hasattr(hf, "solid_normals_at"):
        return np.asarray(hf.solid_normals_at(points_O), dtype=np.float64)
    normals = np.asarray(hf.normals_at(points_O[:, :2]), dtype=np.float64).copy()
    top_z = np.asarray(hf.height_at(points_O[:, :2]), dtype=np.float64)
    on_face = ~(points_O[:, 2] >= top_z - _FACE_TOL_MM)  # NaN height: just off the plate
    if np.any(on_face):
        p = points_O[on_face]
        lx, ly = float(hf.size_mm[0]), float(hf.size_mm[1])
        gaps = np.column_stack([p[:, 0], lx - p[:, 0], p[:, 1], ly - p[:, 1],
                                p[:, 2] + float(hf.thickness_mm)])
        faces = np.array([[-1.0, 0, 0], [1.0, 0, 0], [0, -1.0, 0], [0, 1.0, 0], [0, 0, -1.0]])
        normals[on_face] = faces[np.argmin(np.abs(gaps), axis=1)]
    return normals
