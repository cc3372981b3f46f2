"""Per-point rays of the TSDF kernels: profile registration (paper eq 1) and the active-region
test, shared by the serial integrator (:func:`dm2.fusion.tsdf.kernels._fuse`) and the two-thread
kernel (:func:`dm2.fusion.tsdf.owned_kernels.fuse_owned`) so both count and skip points identically.

Both helpers are inlined into their callers (``inline="always"``): the arithmetic is the same
operations in the same order wherever it runs, which keeps the two-thread fusion bit-identical
to the serial one.
"""

from __future__ import annotations

import numpy as np
from numba import njit

# the pose of a batch of rays given in O (no registration): never read, only unpacked
NO_POSE = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)


@njit(cache=True, inline="always")
def profile_pose(T_O_S, spot_O, axis_O, k):
    """Profile ``k``'s registration constants (15 floats): the x and z columns of ``R_O_S``
    ``(r00, r10, r20, r02, r12, r22)``, the sensor origin ``(ox, oy, oz)`` [mm], the spray spot
    ``(sx, sy, sz)`` [mm] and the spray axis ``(ax, ay, az)``, all in ``O``."""
    return (T_O_S[k, 0, 0], T_O_S[k, 1, 0], T_O_S[k, 2, 0],
            T_O_S[k, 0, 2], T_O_S[k, 1, 2], T_O_S[k, 2, 2],
            T_O_S[k, 0, 3], T_O_S[k, 1, 3], T_O_S[k, 2, 3],
            spot_O[k, 0], spot_O[k, 1], spot_O[k, 2],
            axis_O[k, 0], axis_O[k, 1], axis_O[k, 2])


@njit(cache=True, inline="always")
def point_ray(register, i, pose, xz_S, origins_O, points_O, active, active_r2_mm2, bounds_lo,
              bounds_hi, use_bounds, truncation_mm, counts):
    """The ray of point ``i``: ``ok, ox, oy, oz, dx, dy, dz, r, act``.

    ``register``: point ``xz_S[i]`` of the profile whose :func:`profile_pose` is ``pose``
    (skipped behind the sensor, ``z <= 0``, or with ``use_bounds`` outside
    ``[bounds_lo, bounds_hi]``: ``counts[0] += 1``), active when within
    ``sqrt(active_r2_mm2)`` of the spray axis; else the ray ``origins_O[i] -> points_O[i]``
    with ``active[i]``. A point that is not skipped counts in ``counts[1]``; ``ok`` is False
    for skipped points and for points within ``truncation_mm`` of their origin (no band).
    ``(dx, dy, dz)`` is the unit direction, ``r`` [mm] the range.
    """
    r00, r10, r20, r02, r12, r22, ox, oy, oz, sx, sy, sz, ax, ay, az = pose
    if register:
        x, z = xz_S[i, 0], xz_S[i, 1]
        if not z > 0.0:  # behind the sensor
            counts[0] += 1
            return False, ox, oy, oz, 0.0, 0.0, 0.0, 0.0, False
        px = ox + r00 * x + r02 * z
        py = oy + r10 * x + r12 * z
        pz = oz + r20 * x + r22 * z
        if use_bounds and not (bounds_lo[0] <= px <= bounds_hi[0]
                               and bounds_lo[1] <= py <= bounds_hi[1]
                               and bounds_lo[2] <= pz <= bounds_hi[2]):
            counts[0] += 1
            return False, ox, oy, oz, 0.0, 0.0, 0.0, 0.0, False
        qx, qy, qz = px - sx, py - sy, pz - sz
        along = qx * ax + qy * ay + qz * az
        act = (qx * qx + qy * qy + qz * qz) - along * along <= active_r2_mm2
    else:
        ox, oy, oz = origins_O[i, 0], origins_O[i, 1], origins_O[i, 2]
        px, py, pz = points_O[i, 0], points_O[i, 1], points_O[i, 2]
        act = active[i]
    counts[1] += 1
    dx, dy, dz = px - ox, py - oy, pz - oz
    r = np.sqrt(dx * dx + dy * dy + dz * dz)
    if r <= truncation_mm:
        return False, ox, oy, oz, 0.0, 0.0, 0.0, r, False
    dx /= r
    dy /= r
    dz /= r
    return True, ox, oy, oz, dx, dy, dz, r, act
