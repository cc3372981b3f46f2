"""Carving stale free slabs buried in a grown column, along the build direction.

Why: the ray carve (:mod:`dm2.fusion.tsdf.carve`) fills a free slab that an active ray crosses
within one truncation behind its band. A spot that the profilers see only at grazing angles
gets no such ray: on the reduced twisted tower with its feed 15 % high (paper experiment 1), the
top centre is ringed by a ridge up to 4 mm taller, and rays pass over the centre into the
ridge's inner wall. Each layer they wrote free space over the centre's old top, and the few
rays that reached the new top wrote its band only. So the column held, under the true top, the
free-space voxels of four earlier layers (weights capped to the deposit cap by
:mod:`dm2.pipeline.grown_columns`, never seen again): a stack of surfaces down to 6 mm under the
true top, which the layer analysis called an underbuild of 107 mm2 by layer 19.

How: where the reference grew in a layer (the columns :class:`GrownColumns` caps), the column is
walked down from a truncation above the reference's new height to ``BURIED_DEPTH_MM`` below its
old height. Below the first observed material voxel (``d <= 0``), a run of observed free voxels
(``d > 0``) that the walk leaves into observed material is a free slab enclosed by material
above and below: deposition only adds material on top, so it is material now, if it is stale.
Stale means a weight below ``stale_below``, the caller's cap plus one observation: not seen
again since the column's last cap, but for the low weight behind a new surface where the new
band's edge averaged the old free space with material. The slab becomes inferred material as
the ray carve makes it (``d = -truncation``, weight ``CARVE_WEIGHT``, below the default
``min_weight``: no extracted surface and no real-time crossing until an observation confirms
it). Voxels no ray ever reached (weight 0) inside such a run are enclosed all the same and are
carved with it: on paper experiment 1 the grazing rays over the centre wrote its old free
space in some voxels of a column and skipped the ones between, and such a gap kept the stale
slab. A run that ends in an unallocated voxel, at the end of the walk or at
``CARVE_RUN_VOXELS``, or that holds a free voxel seen again since the last cap, is left alone.
A dent has no observed material above its floor, so nothing in its column is carved.

On paper experiment 1 the false underbuild fell from 107 to 76 mm2 (its peak from 6.4 to 4.3 mm
deep; carving through the never-reached gaps and the last layer's slabs too, to 66 mm2: what is
left are centre columns whose new top no ray reached) and the worst layer's
reconstruction RMS against the truth from 0.355 to 0.231 mm; on the full twisted tower the
worst 8-layer band from 0.360 to 0.343 mm (p95 0.852 to 0.809 mm), 21 tracks to 20.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from dm2.fusion.tsdf.carve import CARVE_RUN_VOXELS, CARVE_WEIGHT
from dm2.fusion.tsdf.kernels import voxel_at


@njit(cache=True, error_model="numpy", nogil=True)
def carve_columns(table_keys, table_slots, voxels, touched, voxel_mm, x_mm, y_mm, z_lo_mm,
                  z_hi_mm, truncation_mm, stale_below):
    """Carve the enclosed stale free runs (module docstring) of the voxel columns holding
    ``(x_mm[k], y_mm[k])``, walked from ``z_hi_mm[k]`` down to ``z_lo_mm[k]`` [mm] (voxels whose
    centre's height falls there); marks the carved blocks touched, returns the voxels carved."""
    n = 0
    run_slot = np.empty(CARVE_RUN_VOXELS, np.int64)
    run_li = np.empty(CARVE_RUN_VOXELS, np.int64)
    for k in range(x_mm.shape[0]):
        ix = int(math.floor(x_mm[k] / voxel_mm))
        iy = int(math.floor(y_mm[k] / voxel_mm))
        iz0 = int(math.floor(z_lo_mm[k] / voxel_mm))
        iz1 = int(math.floor(z_hi_mm[k] / voxel_mm))
        material_above = False
        n_run = 0
        for iz in range(iz1, iz0 - 1, -1):
            slot, li = voxel_at(table_keys, table_slots, ix, iy, iz)
            if slot < 0:
                n_run = -1
                continue
            w = voxels[slot, li, 1]
            if w <= 0.0 or voxels[slot, li, 0] > 0.0:  # unobserved, or observed free
                if material_above and w < stale_below and 0 <= n_run < CARVE_RUN_VOXELS:
                    run_slot[n_run] = slot
                    run_li[n_run] = li
                    n_run += 1
                else:
                    n_run = -1  # seen again, too long or open above: left alone to material
            else:
                for j in range(max(n_run, 0)):
                    voxels[run_slot[j], run_li[j], 0] = -truncation_mm
                    voxels[run_slot[j], run_li[j], 1] = CARVE_WEIGHT
                    touched[run_slot[j]] = True
                n += max(n_run, 0)
                n_run = 0
                material_above = True
    return n
