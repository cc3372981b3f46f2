"""The argument bundles of the TSDF kernels (namedtuples, which numba passes as one argument
each and whose fields it reads like locals).

- :class:`RayBatch`: one batch of input, either rays given in ``O`` (``origins_O``,
  ``points_O``, ``active``) or profiles to register (``xz_S``, ``offsets``, ``T_O_S``,
  ``spot_O``, ``axis_O``, ``active_r2_mm2``, ``bounds_lo``/``bounds_hi``); the fields of the
  other kind hold empty arrays (see :func:`ray_batch` and :func:`profile_batch`);
- :class:`FuseParams`: the band and the weights;
- :class:`BlockStore`: the field's block storage (hash, keys, voxels, touched marks, count);
- :class:`StagedRows`: a thread's staging area for blocks the field lacks, whose voxels live in
  rows ``base + s`` of the field's voxel array (:mod:`dm2.fusion.tsdf.owned_kernels`); the
  serial kernel's is empty with ``base`` the field's capacity.
"""

from __future__ import annotations

from collections import namedtuple

import numpy as np

RayBatch = namedtuple("RayBatch", "origins_O points_O active xz_S offsets T_O_S spot_O axis_O "
                                  "active_r2_mm2 bounds_lo bounds_hi")
FuseParams = namedtuple("FuseParams", "voxel_mm truncation_mm active_weight_cap max_weight")
BlockStore = namedtuple("BlockStore", "table_keys table_slots block_keys voxels touched state")
StagedRows = namedtuple("StagedRows", "base keys table_keys table_slots state")

_NONE3 = np.zeros((0, 3))
_NO_POSES = np.zeros((0, 4, 4))
_NO_ACTIVE = np.zeros(0, dtype=np.bool_)
_NO_BOUNDS = np.zeros(3)


def ray_batch(origins_O: np.ndarray, points_O: np.ndarray, active: np.ndarray) -> RayBatch:
    """Rays ``origins_O[i] -> points_O[i]`` (``(n, 3)`` float64, C order) with ``active (n,)``
    bool: one profile of all ``n`` rays, nothing to register."""
    off = np.array([0, points_O.shape[0]], dtype=np.int64)
    return RayBatch(origins_O, points_O, active, points_O, off, _NO_POSES, _NONE3, _NONE3, 0.0,
                    _NO_BOUNDS, _NO_BOUNDS)


def profile_batch(xz_S, offsets, T_O_S, spot_O, axis_O, active_r2_mm2: float,
                  bounds_lo=_NO_BOUNDS, bounds_hi=_NO_BOUNDS) -> RayBatch:
    """Profiles to register and fuse (arguments as in
    :meth:`dm2.fusion.tsdf.field.SparseTSDF.integrate_profiles`)."""
    return RayBatch(_NONE3, _NONE3, _NO_ACTIVE, xz_S, offsets, T_O_S, spot_O, axis_O,
                    float(active_r2_mm2), bounds_lo, bounds_hi)


def fuse_params(field) -> FuseParams:
    """The band and weights of a :class:`~dm2.fusion.tsdf.field.SparseTSDF`."""
    return FuseParams(field.voxel_mm, field.truncation_mm, field.weight_cap,
                      field.inactive_weight_cap)


def block_store(field) -> BlockStore:
    """The block storage of a :class:`~dm2.fusion.tsdf.field.SparseTSDF` as it is now (its
    arrays are replaced when the field grows)."""
    return BlockStore(field._table_keys, field._table_slots, field.block_keys, field.voxels,
                      field.touched, field._state)
