"""Dense sub-volumes gathered from the sparse TSDF's blocks (:mod:`dm2.fusion.tsdf.field`)."""

from __future__ import annotations

import numpy as np
from numba import njit

from dm2.fusion.tsdf.kernels import BLOCK, BLOCK_SHIFT, hash_find, pack_key


@njit(cache=True, nogil=True)
def gather_dense(table_keys, table_slots, voxels, origin_voxel, shape, fill_mm):
    """Dense ``tsdf (shape)`` and ``weight (shape)`` sub-volumes starting at voxel index
    ``origin_voxel (3,)``; voxels of unallocated blocks get ``fill_mm`` and weight 0."""
    nx, ny, nz = shape[0], shape[1], shape[2]
    out_d = np.full((nx, ny, nz), fill_mm, dtype=np.float32)
    out_w = np.zeros((nx, ny, nz), dtype=np.float32)
    ox, oy, oz = origin_voxel[0], origin_voxel[1], origin_voxel[2]
    # iterate block by block
    bx0, by0, bz0 = ox >> BLOCK_SHIFT, oy >> BLOCK_SHIFT, oz >> BLOCK_SHIFT
    bx1 = (ox + nx - 1) >> BLOCK_SHIFT
    by1 = (oy + ny - 1) >> BLOCK_SHIFT
    bz1 = (oz + nz - 1) >> BLOCK_SHIFT
    for bx in range(bx0, bx1 + 1):
        for by in range(by0, by1 + 1):
            for bz in range(bz0, bz1 + 1):
                s = hash_find(table_keys, table_slots, pack_key(bx, by, bz))
                if s < 0:
                    continue
                for lz in range(BLOCK):
                    gz = bz * BLOCK + lz - oz
                    if gz < 0 or gz >= nz:
                        continue
                    for ly in range(BLOCK):
                        gy = by * BLOCK + ly - oy
                        if gy < 0 or gy >= ny:
                            continue
                        for lx in range(BLOCK):
                            gx = bx * BLOCK + lx - ox
                            if gx < 0 or gx >= nx:
                                continue
                            li = lx + BLOCK * (ly + BLOCK * lz)
                            out_d[gx, gy, gz] = voxels[s, li, 0]
                            out_w[gx, gy, gz] = voxels[s, li, 1]
    return out_d, out_w
