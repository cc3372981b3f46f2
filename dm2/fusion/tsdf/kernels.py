"""Numba kernels of the sparse TSDF: the serial integrator (the walk it shares with the
two-thread update: :mod:`dm2.fusion.tsdf.walk`; block hash: :mod:`dm2.fusion.tsdf.block_hash`;
dense gathering: :mod:`dm2.fusion.tsdf.dense`).

Storage layout (see :mod:`dm2.fusion.tsdf.field`): voxels live in blocks of ``BLOCK**3`` voxels,
found through the block hash, in rows ("slots") of the preallocated ``voxels`` array of shape
``(capacity, 512, 2)`` float32 that keeps each voxel's signed distance [mm] and weight side by
side (one cache line per update).

The integrator walks each sensor ray through the voxel grid from ``truncation`` in front of the
measured point to ``truncation`` behind it and updates every voxel it crosses with the
projective signed distance (eqs 2-3 of the paper). ``fuse_profiles`` also registers the
profiles (eq 1) and decides each point's active region in the same pass.

Arguments come bundled (:mod:`dm2.fusion.tsdf.bundles`): ``batch`` a ``RayBatch``, ``params``
a ``FuseParams``, ``blocks`` the field's ``BlockStore`` (``blocks.state[0]``: allocated blocks).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from dm2.fusion.tsdf.block_hash import (  # noqa: F401  (the field's names for them)
    BLOCK,
    BLOCK_SHIFT,
    BLOCK_VOXELS,
    EMPTY,
    MAX_NEW_BLOCKS_PER_RAY,
    hash_find,
    pack_key,
    rebuild_hash,
    unpack_keys,
)
from dm2.fusion.tsdf.bundles import StagedRows
from dm2.fusion.tsdf.carve import COL_SHIFT
from dm2.fusion.tsdf.walk import fuse_batch


@njit(cache=True, inline="always")
def _no_staging(blocks):
    """The serial walk's staging area: none, its ``base`` past the last row (every carved
    block is marked touched)."""
    return StagedRows(blocks.voxels.shape[0], np.zeros(0, np.int64), np.zeros(0, np.int64),
                      np.zeros(0, np.int32), np.zeros(1, np.int64))


@njit(cache=True, error_model="numpy")
def integrate_rays(batch, start, params, blocks):
    """Fuse the rays ``batch.origins_O[i] -> batch.points_O[i]`` (active: ``batch.active[i]``)
    into the sparse TSDF, from index ``start``. Returns the index of the first ray that was
    not integrated because the block arrays or the hash table need to grow (``n`` when done).
    """
    counts = np.zeros(2, dtype=np.int64)
    return fuse_batch(False, False, False, 0, COL_SHIFT, start, batch, params, blocks,
                      _no_staging(blocks), counts)


@njit(cache=True, error_model="numpy")
def fuse_profiles(batch, use_bounds, start, params, blocks, counts):
    """Register and fuse a batch of profiles (paper eq 1, then eqs 2-5), from point ``start``.

    Profile ``k`` owns points ``xz_S[offsets[k]:offsets[k + 1]]``; its point ``(x, z)`` lies at
    ``p = t + x * R[:, 0] + z * R[:, 2]`` in ``O`` with ``R, t`` of ``T_O_S[k]`` and its ray
    starts at ``t`` (the laser's emission point). A point is active when its distance from the
    nozzle axis through ``spot_O[k]`` along ``axis_O[k]`` is at most ``sqrt(active_r2_mm2)``.
    Points with ``z <= 0`` (behind the sensor) or, with ``use_bounds``, outside
    ``[bounds_lo, bounds_hi]`` are skipped and counted in ``counts[0]``; fused points are
    counted in ``counts[1]``. Returns the index of the first point not handled because the
    block arrays or the hash table need to grow (``len(xz_S)`` when done).

    Weights: ``w_A = 1`` over the whole band in the active region; ``w_I = 1`` in front and
    ``1 - behind / truncation`` behind the point elsewhere (eqs 4-5). In the active region the
    stored weight is first capped at ``active_weight_cap``, and the walk goes on beyond the
    band, carving enclosed stale free space (:mod:`dm2.fusion.tsdf.carve`).
    """
    staged = _no_staging(blocks)
    if use_bounds:  # literal flags: each variant is compiled without the other's tests
        return fuse_batch(False, True, True, 0, COL_SHIFT, start, batch, params, blocks, staged,
                          counts)
    return fuse_batch(False, True, False, 0, COL_SHIFT, start, batch, params, blocks, staged,
                      counts)
