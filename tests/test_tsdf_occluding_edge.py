"""A profile point on an occluding edge writes no band behind it (dm2.fusion.tsdf.point_rays):
past the edge its ray runs through free space the sensor never saw (the shadow), which the band
would fill with material. The end-to-end case is the regression bench's plate with a hole,
whose last real-time false alarm was such a band (tests/test_bench_regression.py)."""

from __future__ import annotations

import numpy as np

from dm2.fusion.tsdf.point_rays import behind_scale


def _step_profile(fan_rad: np.ndarray) -> np.ndarray:
    """``(x_S, z_S)`` along the fan of a sensor 40 mm to the -x side of a 2 mm step (top at
    ``x_O < 0``, floor beyond) and 60 mm up, its ``x_S`` along ``+x_O`` (``x_O = x_S - 40``)
    and ``z_S`` straight down: the top where a ray meets it, else the floor beyond the corner's
    shadow (``x_O > 1.38`` mm)."""
    t = np.where(-40.0 + 58.0 * np.tan(fan_rad) < 0.0, 58.0, 60.0) / np.cos(fan_rad)
    return np.column_stack([t * np.sin(fan_rad), t * np.cos(fan_rad)])


def test_the_last_point_before_a_depth_step_is_the_only_occluding_edge():
    """Across the step the range jumps by 2.5 mm: the top's last point is the edge; the floor's
    first point beyond the shadow (the far side) and every other point keep their band."""
    xz = _step_profile(np.radians(np.linspace(30.0, 40.0, 640)))
    scale = np.array([behind_scale(xz, i, 0, len(xz)) for i in range(len(xz))])
    edge = int(np.argmax(np.diff(np.hypot(xz[:, 0], xz[:, 1]))))  # the last point on the top
    assert xz[edge, 0] - 40.0 < 0.0 < xz[edge + 1, 0] - 40.0  # the top, then the floor
    assert scale[edge] == 0.0 and np.count_nonzero(scale == 0.0) == 1
    assert behind_scale(xz[::-1].copy(), len(xz) - 1 - edge, 0, len(xz)) == 0.0  # either order
