"""Per-point rays of the TSDF kernels: profile registration (paper eq 1), the active-region
test and the occluding-edge test of the band behind a point (:func:`behind_scale`), shared by
the serial integrator (:func:`dm2.fusion.tsdf.kernels._fuse`) and the two-thread kernel
(:func:`dm2.fusion.tsdf.owned_kernels.fuse_owned`) so both count and skip points identically.

The helpers are inlined into their callers (``inline="always"``): the arithmetic is the same
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
def point_ray(register, i, pose, xz_S, origins_O, points_O, active, count, active_r2_mm2,
              bounds_lo, bounds_hi, use_bounds, truncation_mm, counts):
    """The ray of point ``i``: ``ok, ox, oy, oz, dx, dy, dz, r, act``.

    ``register``: point ``xz_S[i]`` of the profile whose :func:`profile_pose` is ``pose``
    (skipped behind the sensor, ``z <= 0``, or with ``use_bounds`` outside
    ``[bounds_lo, bounds_hi]``: ``counts[0] += count[i]``), active when within
    ``sqrt(active_r2_mm2)`` of the spray axis; else the ray ``origins_O[i] -> points_O[i]``
    with ``active[i]``. A point that is not skipped counts in ``counts[1]`` (``count[i]``, the
    measured points it stands for); ``ok`` is False for skipped points and for points within
    ``truncation_mm`` of their origin (no band).
    ``(dx, dy, dz)`` is the unit direction, ``r`` [mm] the range.
    """
    r00, r10, r20, r02, r12, r22, ox, oy, oz, sx, sy, sz, ax, ay, az = pose
    if register:
        x, z = xz_S[i, 0], xz_S[i, 1]
        if not z > 0.0:  # behind the sensor
            counts[0] += count[i]
            return False, ox, oy, oz, 0.0, 0.0, 0.0, 0.0, False
        px = ox + r00 * x + r02 * z
        py = oy + r10 * x + r12 * z
        pz = oz + r20 * x + r22 * z
        if use_bounds and not (bounds_lo[0] <= px <= bounds_hi[0]
                               and bounds_lo[1] <= py <= bounds_hi[1]
                               and bounds_lo[2] <= pz <= bounds_hi[2]):
            counts[0] += count[i]
            return False, ox, oy, oz, 0.0, 0.0, 0.0, 0.0, False
        qx, qy, qz = px - sx, py - sy, pz - sz
        along = qx * ax + qy * ay + qz * az
        act = (qx * qx + qy * qy + qz * qz) - along * along <= active_r2_mm2
    else:
        ox, oy, oz = origins_O[i, 0], origins_O[i, 1], origins_O[i, 2]
        px, py, pz = points_O[i, 0], points_O[i, 1], points_O[i, 2]
        act = active[i]
    counts[1] += count[i]
    dx, dy, dz = px - ox, py - oy, pz - oz
    r = np.sqrt(dx * dx + dy * dy + dz * dz)
    if r <= truncation_mm:
        return False, ox, oy, oz, 0.0, 0.0, 0.0, r, False
    dx /= r
    dy /= r
    dz /= r
    return True, ox, oy, oz, dx, dy, dz, r, act


# a neighbour in the profile this much farther from the sensor: the point is on an occluding
# edge (two voxels at the default 0.5 mm)
EDGE_JUMP_MM = 1.0


@njit(cache=True, inline="always")
def behind_scale(xz_S, i, lo, hi):
    """The weight factor of the band behind point ``i`` of the profile ``xz_S[lo:hi]`` (its
    points in order along the laser line): 0 where the point is the near side of an occluding
    edge, a neighbour lying more than ``EDGE_JUMP_MM`` farther from the sensor; else 1. Behind
    such a point the ray leaves the part past the edge into the edge's shadow, free space the
    sensor never saw, where the band would write material: a false surface that a real-time
    comparison reads as overbuild (on a fault-free plate with a hole, 0.3 mm over the true
    dimple, an alarm). Points with no jump beside them keep their band; so do the far sides
    of jumps."""
    xi, zi = xz_S[i, 0], xz_S[i, 1]
    ri = np.sqrt(xi * xi + zi * zi)
    if i > lo:
        x, z = xz_S[i - 1, 0], xz_S[i - 1, 1]
        if np.sqrt(x * x + z * z) - ri > EDGE_JUMP_MM:
            return 0.0
    if i < hi - 1:
        x, z = xz_S[i + 1, 0], xz_S[i + 1, 1]
        if np.sqrt(x * x + z * z) - ri > EDGE_JUMP_MM:
            return 0.0
    return 1.0


@njit(cache=True, inline="always")
def _ray_farther(origins_O, points_O, i, j, r_i):
    """Whether ray ``j`` leaves ray ``i``'s origin and reaches more than ``EDGE_JUMP_MM``
    farther (range ``r_i`` [mm])."""
    if origins_O[j, 0] != origins_O[i, 0] or origins_O[j, 1] != origins_O[i, 1] or \
            origins_O[j, 2] != origins_O[i, 2]:
        return False
    dx = points_O[j, 0] - origins_O[j, 0]
    dy = points_O[j, 1] - origins_O[j, 1]
    dz = points_O[j, 2] - origins_O[j, 2]
    return np.sqrt(dx * dx + dy * dy + dz * dz) - r_i > EDGE_JUMP_MM


@njit(cache=True, inline="always")
def ray_behind_scale(origins_O, points_O, i, n, r_i):
    """:func:`behind_scale` for rays given in ``O`` (``n`` of them, ray ``i`` of range ``r_i``
    [mm]): consecutive rays from the same origin are a profile's points in order, so a ray is
    an occluding edge where such a neighbour reaches more than ``EDGE_JUMP_MM`` farther."""
    if i > 0 and _ray_farther(origins_O, points_O, i, i - 1, r_i):
        return 0.0
    if i < n - 1 and _ray_farther(origins_O, points_O, i, i + 1, r_i):
        return 0.0
    return 1.0
