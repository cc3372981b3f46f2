"""Geometric model of a laser profiler scanning the sphere artifact (prediction, no noise).

The fan is emitted from the origin of ``S`` in the ``x_S``-``z_S`` plane, its rays spaced evenly
in ``x`` at ``z_end`` (the sensor's documented profile layout); valid points lie in
the trapezoid ``z_S in [z_start, z_end]``, ``|x_S| <= width(z_S) / 2`` with the width growing
linearly from ``x_width_start_mm`` to ``x_width_end_mm``, and must be seen by the
triangulation camera at ``(0, camera_baseline_mm, 0)`` in ``S``. Occluders (the nozzle body)
are finite cylinders in ``B``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calib.artifact import Artifact, ray_cylinder
from dm2.core.config import SensorConfig
from dm2.core.frames import apply, invert, rotate
from dm2.core.tolerances import OCCLUSION_SLACK_MM


@dataclass(frozen=True)
class FanModel:
    """The profiler's field of view and ray fan (all lengths in mm)."""

    z_start_mm: float
    z_end_mm: float
    x_width_start_mm: float
    x_width_end_mm: float
    points: int
    camera_baseline_mm: float

    @classmethod
    def from_config(cls, sensors: SensorConfig) -> FanModel:
        return cls(sensors.z_start_mm, sensors.z_end_mm, sensors.x_width_start_mm,
                   sensors.x_width_end_mm, sensors.points, sensors.camera_baseline_mm)

    def half_width_mm(self, z_mm: np.ndarray) -> np.ndarray:
        f = (np.asarray(z_mm) - self.z_start_mm) / (self.z_end_mm - self.z_start_mm)
        return 0.5 * (self.x_width_start_mm + f * (self.x_width_end_mm - self.x_width_start_mm))

    def ray_dirs_S(self) -> np.ndarray:
        """Unit ray directions (points, 3) of the fan, ordered by increasing x_S.

        As the sensor documents its profile (and the twin's profiler emits it), the points are
        spaced evenly in x at the end of the measuring range, ``x_width_end_mm`` wide there;
        that is not even in angle (the outer rays lie closer in angle).
        """
        half = 0.5 * self.x_width_end_mm
        x = np.linspace(-half, half, self.points)
        d = np.column_stack([x, np.zeros_like(x), np.full_like(x, self.z_end_mm)])
        return d / np.linalg.norm(d, axis=1, keepdims=True)

    def in_view(self, xz_S: np.ndarray) -> np.ndarray:
        """(n,) bool: points inside the measuring trapezoid (NaN is outside)."""
        x, z = xz_S[:, 0], xz_S[:, 1]
        with np.errstate(invalid="ignore"):
            return ((z >= self.z_start_mm) & (z <= self.z_end_mm)
                    & (np.abs(x) <= self.half_width_mm(z)))

    @property
    def camera_S(self) -> np.ndarray:
        return np.array([0.0, self.camera_baseline_mm, 0.0])


@dataclass(frozen=True)
class Cylinder:
    """An occluding finite cylinder: its axis is ``+z_C`` of ``T_B_C`` from 0 to ``length_mm``.

    Any object with ``T_B_C``, ``radius_mm``, ``length_mm`` and ``hit_t(origins_B, dirs_B)``
    (distance along unit rays, inf on a miss) serves as an occluder.
    """

    T_B_C: np.ndarray
    radius_mm: float
    length_mm: float

    def hit_t(self, origins_B: np.ndarray, dirs_B: np.ndarray) -> np.ndarray:
        T = np.asarray(self.T_B_C, dtype=np.float64)
        return ray_cylinder(origins_B, dirs_B, T[:3, 3], T[:3, 2], self.radius_mm,
                            self.length_mm)


def _blocked(artifact: Artifact, T_A_B: np.ndarray, occluders, o_B, d_B, length):
    """(n,) bool: segments from ``o_B`` along ``d_B`` hit something before ``length``."""
    t_art, _ = artifact.raycast_A(apply(T_A_B, o_B), rotate(T_A_B, d_B))
    blocked = t_art < length - OCCLUSION_SLACK_MM
    for occ in occluders:
        blocked |= occ.hit_t(o_B, d_B) < length - OCCLUSION_SLACK_MM
    return blocked


def scan_artifact(artifact: Artifact, T_B_A: np.ndarray, T_B_S: np.ndarray, fan: FanModel,
                  occluders: tuple[Cylinder, ...] = ()) -> tuple[np.ndarray, np.ndarray]:
    """Noise-free profile of the artifact at pose ``T_B_A`` seen by the sensor at ``T_B_S``.

    Returns
    -------
    xz_S : (points, 2) float64 [mm], NaN where no valid point
    feature : (points,) int64, sphere index per point, -2 post/plate, -1 invalid
    """
    T_A_B = invert(T_B_A)
    d_S = fan.ray_dirs_S()
    n = d_S.shape[0]
    o_B = np.repeat(T_B_S[None, :3, 3], n, axis=0)
    d_B = rotate(T_B_S, d_S)
    t, feature = artifact.raycast_A(apply(T_A_B, o_B), rotate(T_A_B, d_B))
    for occ in occluders:
        t_occ = occ.hit_t(o_B, d_B)
        nozzle_first = t_occ < t
        t = np.where(nozzle_first, np.inf, t)
    hit = np.isfinite(t)
    p_S = d_S * np.where(hit, t, np.nan)[:, None]
    xz = p_S[:, [0, 2]]
    valid = hit & fan.in_view(xz)
    if np.any(valid):
        p_B = apply(T_B_S, p_S[valid])
        cam_B = apply(T_B_S, fan.camera_S[None])[0]
        v = p_B - cam_B
        length = np.linalg.norm(v, axis=1)
        seen = ~_blocked(artifact, T_A_B, occluders, np.repeat(cam_B[None], len(v), axis=0),
                         v / length[:, None], length)
        idx = np.flatnonzero(valid)
        valid[idx[~seen]] = False
    xz[~valid] = np.nan
    feature = np.where(valid, feature, -1)
    return xz, feature
