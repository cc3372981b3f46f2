"""Argument bundles of the TSDF kernels (:mod:`dm2.fusion.tsdf.kernels`,
:mod:`dm2.fusion.tsdf.owned_kernels`): immutable namedtuples of arrays and scalars that numba
passes by value (a heterogeneous namedtuple is a struct, its fields read at no cost).

The arrays inside are the field's own and are written in place by the kernels; only the bundle
is immutable. The literal flags ``register`` and ``use_bounds`` are never bundled: they stay
separate arguments so that each variant of a kernel is compiled with them as constants.
Build a new bundle whenever an array is replaced (the field's ``_grow``).

Bundles cost nothing between compiled functions, but numba types a namedtuple argument of a
call from Python slowly, about 0.6 us each (its fingerprint is not on the fast path that
arrays, scalars and plain tuples take): an empty batch through ``fuse_profiles`` took 3.6 us
with its three bundles (5.1 us with building them), 1.6 us with plain tuples and 1.3 us with
21 flat arguments. So the kernels called from Python once per profile
(:func:`~dm2.fusion.tsdf.kernels.fuse_profiles`, ``integrate_rays``) take flat arrays and
build the bundles inside, with :func:`ray_batch` and :func:`profile_batch` (compiled, callable
from Python too); the two-thread kernels, called twice per batch of thousands of points, take
bundles.
"""

from __future__ import annotations

from collections import namedtuple

import numpy as np
from numba import njit

BlockHash = namedtuple("BlockHash", ["keys", "slots"])
BlockHash.__doc__ = """Open-addressing hash of packed block keys: ``keys (size,)`` int64
(``EMPTY`` marks a free entry) and ``slots (size,)`` int32, the block row of each key; ``size``
is a power of two."""

FusionParams = namedtuple("FusionParams", [
    "voxel_mm", "truncation_mm", "active_weight_cap", "max_weight", "active_r2_mm2",
    "bounds_lo", "bounds_hi"])
FusionParams.__doc__ = """Constants of one fusion call: ``voxel_mm`` [mm] voxel edge,
``truncation_mm`` [mm] half width of the band, ``active_weight_cap`` (stored weight clipped to
this before an active update), ``max_weight`` (stored weights never exceed this),
``active_r2_mm2`` [mm^2] squared active radius around the spray axis (profiles only),
``bounds_lo, bounds_hi (3,)`` float64 [mm, O] the box of points fused (read only with the
``use_bounds`` flag)."""

Batch = namedtuple("Batch", [
    "origins_O", "points_O", "active", "xz_S", "offsets", "T_O_S", "spot_O", "axis_O", "count"])
Batch.__doc__ = """One batch of rays (read with ``register=False``) or of profiles
(``register=True``); the other kind's fields are empty (:func:`ray_batch`,
:func:`profile_batch`). Rays: ``origins_O, points_O (n, 3)`` float64 [mm, O] and
``active (n,)`` bool. Profiles: ``xz_S (n, 2)`` float64 [mm, S] laser-plane points, profile
``k`` owning ``xz_S[offsets[k]:offsets[k + 1]]`` (``offsets (k + 1,)`` int64; for rays
``[0, n]``), ``T_O_S (k, 4, 4)`` float64 sensor poses in ``O``, ``spot_O (k, 3)`` float64
[mm, O] deposition spot and ``axis_O (k, 3)`` float64 unit spray axis in ``O``. Both kinds:
``count (n,)`` int64, how many measured points each ray stands for (its weight's multiple:
:mod:`dm2.fusion.profile_merge`; 1 for rays given in ``O``)."""

Staging = namedtuple("Staging", ["keys", "table_keys", "table_slots", "state"])
Staging.__doc__ = """One thread's blocks allocated during a two-thread run: ``keys
(capacity,)`` int64 in allocation order, their hash (``table_keys (2 capacity,)`` int64,
``table_slots (2 capacity,)`` int32, a power of two) and ``state (1,)`` int64 (``state[0]``:
blocks staged). The staged blocks' voxels live in the field's own voxel array, in rows
reserved for the thread (``base + s`` for staged block ``s``)."""


def new_staging(capacity: int = 1024) -> Staging:
    """An empty :class:`Staging` area of ``capacity`` blocks."""
    return Staging(np.full(capacity, -1, dtype=np.int64),
                   np.full(2 * capacity, -1, dtype=np.int64),
                   np.full(2 * capacity, -1, dtype=np.int32),
                   np.zeros(1, dtype=np.int64))


@njit(cache=True, nogil=True)
def ray_batch(origins_O, points_O, active):
    """A :class:`Batch` of rays ``origins_O[i] -> points_O[i]`` (C-contiguous float64 ``(n, 3)``
    [mm, O], ``active (n,)`` bool), one "profile" of all points; the profile fields hold no
    profile (``xz_S`` is ``points_O``, never read)."""
    offsets = np.array([0, points_O.shape[0]], dtype=np.int64)
    none3 = np.zeros((0, 3))
    return Batch(origins_O, points_O, active, points_O, offsets, np.zeros((0, 4, 4)), none3,
                 none3, np.ones(points_O.shape[0], dtype=np.int64))


@njit(cache=True, nogil=True)
def profile_batch(xz_S, offsets, T_O_S, spot_O, axis_O, count):
    """A :class:`Batch` of profiles (C-contiguous arrays as in :class:`Batch`); the ray fields
    are empty."""
    none3 = np.zeros((0, 3))
    return Batch(none3, none3, np.zeros(0, np.bool_), xz_S, offsets, T_O_S, spot_O, axis_O,
                 count)
