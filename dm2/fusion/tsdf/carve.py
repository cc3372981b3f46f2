"""Carving buried free space behind fresh deposition, shared (inlined) by the serial TSDF kernel
(:func:`dm2.fusion.tsdf.kernels._fuse`) and the two-thread one
(:func:`dm2.fusion.tsdf.owned_kernels.fuse_owned`).

Why: deposition adds material on top of the surface the sensors saw before. When a spot rises
by more than the band reaches behind the new surface between two observations (the band is
``truncation`` along the ray: 1.2 mm vertically at 55 degrees elevation, less than a double
layer), the old surface's free-space voxels are never updated again and stay inside the part as
a buried surface. On the twisted tower these made 98 % of the squared error of layer 55 (1.9 %
of its vertices, 2 to 22 mm below the true top) and the layer RMS grew by about 0.02 mm per
layer; with the carve it stays at 0.11 to 0.13 mm over 56 layers.

How: an *active* ray (its point is in the deposition region) walks on ``CARVE_TRUNCATIONS``
truncations beyond its band, through allocated blocks only. There, a run of observed voxels
that still claim free space (``d > 0``) which the ray leaves into observed material (``d <= 0``)
is a thin free slab enclosed by material: it becomes material (``d = -truncation``). A run that
ends in unobserved space or at the end of the walk is left alone: that is where a ray that
entered the top near an edge leaves the part through a wall, and the free space outside the
wall is real.

The carved material is inferred, not measured, and is sometimes wrong: a ray through a rim
whose walk leaves it into the open space over a concave floor beyond (a hole's dimple) meets
the floor's material too, and the run it carves is real free space. So a carved voxel gets the
weight ``CARVE_WEIGHT``, below the monitor's default ``min_weight``: it ends the buried
surface's crossing, and takes part in no extracted surface and no real-time crossing until an
observation confirms it (or outweighs it). With weight 1 the dimple on the plate with a hole
showed a false surface up to 0.85 mm above its floor, which the real-time comparison
flagged as overbuild.

The two-thread kernel deals block columns to its threads and a thread reads only its own
voxels, so a free run also ends where the walk enters another block column (``2**COL_SHIFT``
blocks wide); the serial kernel ends runs there too, which keeps the two bit-identical.
"""

from __future__ import annotations

import numpy as np
from numba import njit

CARVE_TRUNCATIONS = 1.0  # the walk beyond the band [truncations]
# a carved voxel's weight: inferred material, below the monitor's default min_weight (1), so it
# takes part in no extracted surface and no real-time crossing until an observation confirms it
CARVE_WEIGHT = 0.5
CARVE_RUN_VOXELS = 32    # longest free run that can be carved (a 1.5 mm walk crosses <= 10)
COL_SHIFT = 2            # the two-thread update deals block columns 2**COL_SHIFT blocks wide


@njit(cache=True, inline="always")
def walk_columns(ox, oy, dx, dy, r, truncation_mm, extra_mm, inv_vox, cs):
    """Column range ``(cx0, cx1, cy0, cy1)`` (columns of ``2**cs`` voxels) of a ray's walk from
    ``r - truncation_mm`` to ``r + truncation_mm + extra_mm``, one voxel of margin for rounding."""
    t0, t1 = r - truncation_mm, r + truncation_mm + extra_mm
    ax0, ax1 = (ox + dx * t0) * inv_vox, (ox + dx * t1) * inv_vox
    ay0, ay1 = (oy + dy * t0) * inv_vox, (oy + dy * t1) * inv_vox
    cx0 = (int(np.floor(min(ax0, ax1))) - 1) >> cs
    cx1 = (int(np.floor(max(ax0, ax1))) + 1) >> cs
    cy0 = (int(np.floor(min(ay0, ay1))) - 1) >> cs
    cy1 = (int(np.floor(max(ay0, ay1))) + 1) >> cs
    return cx0, cx1, cy0, cy1


@njit(cache=True, inline="always")
def carve_visit(voxels, slot, vx, vy, vz, truncation_mm, run, n_run, touched, mark_below):
    """One voxel of the walk beyond the band (``slot`` -1: not allocated). ``run (k, 2)`` holds
    ``(slot, voxel index)`` of the ``n_run`` free voxels met since the last material voxel;
    returns the new ``n_run``. Reaching material carves the run (blocks below ``mark_below``
    marked touched: the two-thread kernel's staged rows are marked when committed)."""
    if slot < 0:
        return 0
    li = (vx & 7) + 8 * ((vy & 7) + 8 * (vz & 7))
    if voxels[slot, li, 1] <= 0.0:
        return 0
    if voxels[slot, li, 0] > 0.0:
        if n_run < run.shape[0]:
            run[n_run, 0] = slot
            run[n_run, 1] = li
            return n_run + 1
        return 0
    for j in range(n_run):
        s = run[j, 0]
        voxels[s, run[j, 1], 0] = -truncation_mm
        voxels[s, run[j, 1], 1] = CARVE_WEIGHT
        if s < mark_below:
            touched[s] = True
    return 0
