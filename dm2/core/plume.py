"""The nominal plume width: one formula shared by fusion's active region and the near-net
reference (:mod:`dm2.reference.model`, whose docstring derives it).

``sigma = process.plume_sigma_mm`` when given, else half the plume radius at the standoff, the
plume widening from the nozzle exit with the half angle ``process.plume_half_angle_deg``:
``sigma = (nozzle_exit_mm / 2 + standoff_mm * tan(a)) / 2`` (6.55 mm exit, 30 mm standoff,
5 deg: 2.95 mm).
"""

from __future__ import annotations

import math

PLUME_HALF_ANGLE_DEG = 5.0  # used when the process config has no plume_half_angle_deg


def plume_sigma_mm(process) -> float:
    """Standard deviation of the nominal Gaussian footprint [mm] (see module docstring)."""
    if process.plume_sigma_mm is not None:
        return float(process.plume_sigma_mm)
    half_angle = getattr(process, "plume_half_angle_deg", PLUME_HALF_ANGLE_DEG)
    radius = 0.5 * process.nozzle_exit_mm + process.standoff_mm * math.tan(
        math.radians(half_angle))
    return 0.5 * radius
