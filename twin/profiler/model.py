"""What a virtual profiler's scan produces before its noise: why a point is missing, and the
noise-free trace. Shared by the compiled path (:mod:`twin.profiler.sensor`) and the plain-numpy
fallback (:mod:`twin.profiler.numpy_path`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dm2.core.tolerances import OCCLUSION_SLACK_MM

# Why a point is missing (ProfileTrace.reason).
VALID = 0
NO_SURFACE = 1  # nothing hit inside the measuring range
LASER_BLOCKED = 2  # an occluder (nozzle, robot) stops the laser before the surface
CAMERA_SHADOW = 3  # the deposit or plate hides the lit spot from the camera
CAMERA_BLOCKED = 4  # an occluder hides the lit spot from the camera
BACK_FACING = 5  # the camera looks at the back of the lit surface
TOO_DARK = 6  # incidence so grazing that the return is below the intensity floor
DROPOUT = 7  # random loss
REASONS = ("valid", "no_surface", "laser_blocked", "camera_shadow", "camera_blocked",
           "back_facing", "too_dark", "dropout")

_LIFT_MM = 0.01  # camera rays start this far off the surface, along its normal
_FACE_TOL_MM = OCCLUSION_SLACK_MM  # hits this far below the top surface lie on a plate face



@dataclass(frozen=True)
class ProfileTrace:
    """Noise-free result of one scan, before the sensor's noise and output format.

    Attributes
    ----------
    range_mm : (n,) float64 [mm], distance from the S origin to the lit point (inf: no hit)
    reason : (n,) int8, ``VALID`` or why the point is missing (see ``REASONS``)
    cos_incidence : (n,) float64, cosine between the surface normal and the reversed laser ray
    points_O : (n, 3) float64 [mm], lit points in O (NaN where there is no hit)
    """

    range_mm: np.ndarray
    reason: np.ndarray
    cos_incidence: np.ndarray
    points_O: np.ndarray


def first_occluder_hit(occluders, origins_B: np.ndarray, dirs_B: np.ndarray) -> np.ndarray:
    t = np.full(origins_B.shape[0], np.inf)
    for occ in occluders:
        t = np.minimum(t, occ.hit_t(origins_B, dirs_B))
    return t
