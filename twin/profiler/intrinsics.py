"""Intrinsic errors of a virtual profiler: what its factory calibration gets wrong.

A profiler reports each point as ``(x_S, z_S)`` from its own calibration of the camera and the
laser fan. An intrinsic error is a difference between those reported coordinates and where the
lit point really lies in the laser plane; the pose ``T_B_S`` cannot absorb it entirely.

Model (``x, z``: the true point in the laser plane, ``theta = atan(x / z)`` its fan angle)::

    z_reported = z * (1 + z_scale_error)
    x_reported = z * tan(theta + fan_angle_offset) + x_distortion_mm * u**3 * z / z_end

- ``z_scale_error``: the triangulation range is scaled about the sensor origin (about 0.1 %
  on a 29xx-50 at the end of its range, i.e. 0.1 mm at 120 mm);
- ``fan_angle_offset_rad``: the fan's zero angle is off; mostly a rotation about ``y_S``
  (absorbed by the pose), the remainder is a shear;
- ``x_distortion_mm``: a cubic distortion across the fan, ``u = tan(theta) / tan(theta_max)``
  in ``[-1, 1]`` at the fan's edges, worth ``x_distortion_mm`` at the edge at ``z_end``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dm2.core.config import SensorConfig
from dm2.core.messages import Profile


@dataclass(frozen=True)
class IntrinsicError:
    """One profiler's intrinsic error (see the module docstring)."""

    z_scale_error: float = 0.0
    fan_angle_offset_rad: float = 0.0
    x_distortion_mm: float = 0.0

    def __post_init__(self):
        for name in ("z_scale_error", "fan_angle_offset_rad", "x_distortion_mm"):
            if not np.isfinite(getattr(self, name)):
                raise ValueError(f"IntrinsicError.{name}: must be finite")

    @property
    def is_zero(self) -> bool:
        return (self.z_scale_error == 0.0 and self.fan_angle_offset_rad == 0.0
                and self.x_distortion_mm == 0.0)

    def reported_xz(self, xz_S: np.ndarray, sensors: SensorConfig) -> np.ndarray:
        """Reported ``(n, 2)`` coordinates [mm] of true laser-plane points ``xz_S`` (NaN stays)."""
        xz = np.asarray(xz_S, dtype=np.float64)
        x, z = xz[:, 0], xz[:, 1]
        tan_max = 0.5 * sensors.x_width_end_mm / sensors.z_end_mm
        with np.errstate(invalid="ignore", divide="ignore"):
            theta = np.arctan2(x, z)
            u = np.tan(theta) / tan_max
            x_rep = (z * np.tan(theta + self.fan_angle_offset_rad)
                     + self.x_distortion_mm * u ** 3 * z / sensors.z_end_mm)
        return np.column_stack([x_rep, z * (1.0 + self.z_scale_error)])

    def apply(self, profile: Profile, sensors: SensorConfig) -> Profile:
        """The profile as this sensor reports it (points leaving the range become invalid)."""
        if self.is_zero:
            return profile
        xz = self.reported_xz(profile.xz_S, sensors)
        valid = profile.valid & np.isfinite(xz[:, 1])
        with np.errstate(invalid="ignore"):
            valid &= (xz[:, 1] >= sensors.z_start_mm) & (xz[:, 1] <= sensors.z_end_mm)
        xz[~valid] = np.nan
        intensity = np.where(valid, profile.intensity, 0.0).astype(np.float32)
        return Profile(profile.sensor_id, profile.stamp_s, profile.counter, xz, valid, intensity)


def seeded_intrinsic_errors(sensor_ids, rng: np.random.Generator, z_scale_error: float,
                            fan_angle_offset_deg: float,
                            x_distortion_mm: float) -> dict[str, IntrinsicError]:
    """Per sensor: each magnitude with a seeded random sign (the magnitudes are the sizes)."""
    out = {}
    for sid in sensor_ids:
        s = rng.choice([-1.0, 1.0], 3)
        out[sid] = IntrinsicError(float(s[0] * z_scale_error),
                                  float(s[1] * np.radians(fan_angle_offset_deg)),
                                  float(s[2] * x_distortion_mm))
    return out
