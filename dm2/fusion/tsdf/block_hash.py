"""The sparse TSDF's block hash: block keys, the open-addressing table that maps a key to its row
("slot") of the voxel array, and the two-entry cache of the blocks looked up last.

A block's integer coordinates ``(bx, by, bz)`` are packed into one non-negative int64 key and
found through an open-addressing hash table (linear probing, ``EMPTY`` marks a free entry). Used
by the serial and the two-thread kernels alike (:mod:`dm2.fusion.tsdf.kernels`,
:mod:`dm2.fusion.tsdf.owned_kernels`, the shared walk :mod:`dm2.fusion.tsdf.ray_fuse`).
"""

from __future__ import annotations

import numpy as np
from numba import njit

BLOCK = 8  # voxels per block edge
BLOCK_SHIFT = 3
BLOCK_VOXELS = BLOCK**3
EMPTY = -1
_OFFSET = 1 << 20  # block coordinates in [-2**20, 2**20) pack into 21 bits each
_MASK21 = (1 << 21) - 1
# Worst case of new blocks one ray can need: rays span at most 2 * truncation, a few blocks.
MAX_NEW_BLOCKS_PER_RAY = 16


@njit(cache=True, inline="always")
def pack_key(bx, by, bz):
    return ((bx + _OFFSET) << 42) | ((by + _OFFSET) << 21) | (bz + _OFFSET)


@njit(cache=True)
def unpack_keys(keys):
    """Block coordinates ``(n, 3)`` int64 of packed keys ``(n,)``."""
    out = np.empty((keys.shape[0], 3), dtype=np.int64)
    for i in range(keys.shape[0]):
        k = keys[i]
        out[i, 0] = ((k >> 42) & _MASK21) - _OFFSET
        out[i, 1] = ((k >> 21) & _MASK21) - _OFFSET
        out[i, 2] = (k & _MASK21) - _OFFSET
    return out


@njit(cache=True, inline="always")
def _hash(key, mask):
    h = np.uint64(key) * np.uint64(0x9E3779B97F4A7C15)
    return np.int64(h >> np.uint64(40)) & mask


@njit(cache=True, inline="always")
def hash_find(table_keys, table_slots, key):
    """Slot of ``key`` or -1."""
    mask = table_keys.shape[0] - 1
    h = _hash(key, mask)
    while True:
        k = table_keys[h]
        if k == key:
            return table_slots[h]
        if k == EMPTY:
            return -1
        h = (h + 1) & mask


@njit(cache=True, inline="always")
def voxel_at(table_keys, table_slots, ix, iy, iz):
    """``(slot, index within the block)`` of voxel ``(ix, iy, iz)``; slot -1: not stored."""
    slot = hash_find(table_keys, table_slots,
                     pack_key(ix >> BLOCK_SHIFT, iy >> BLOCK_SHIFT, iz >> BLOCK_SHIFT))
    li = (ix & (BLOCK - 1)) + BLOCK * ((iy & (BLOCK - 1)) + BLOCK * (iz & (BLOCK - 1)))
    return slot, li


@njit(cache=True)
def hash_insert(table_keys, table_slots, key, slot):
    mask = table_keys.shape[0] - 1
    h = _hash(key, mask)
    while table_keys[h] != EMPTY:
        h = (h + 1) & mask
    table_keys[h] = key
    table_slots[h] = slot


@njit(cache=True, nogil=True)
def rebuild_hash(block_keys, n_blocks, table_size):
    """A fresh hash table of ``table_size`` (power of two) entries for the first blocks."""
    table_keys = np.full(table_size, EMPTY, dtype=np.int64)
    table_slots = np.full(table_size, -1, dtype=np.int32)
    for s in range(n_blocks):
        hash_insert(table_keys, table_slots, block_keys[s], s)
    return table_keys, table_slots


@njit(cache=True, inline="always")
def hash_get_or_insert(key, table_keys, table_slots, block_keys, state):
    """Slot of ``key``; a new block (slot ``state[0]``, counted up) when it has none yet."""
    mask = table_keys.shape[0] - 1
    h = _hash(key, mask)
    while True:
        k = table_keys[h]
        if k == key:
            return table_slots[h]
        if k == EMPTY:
            s = state[0]
            state[0] += 1
            table_keys[h] = key
            table_slots[h] = s
            block_keys[s] = key
            return s
        h = (h + 1) & mask


@njit(cache=True, inline="always")
def _get_or_alloc(bx, by, bz, table_keys, table_slots, block_keys, touched, state):
    s = hash_get_or_insert(pack_key(bx, by, bz), table_keys, table_slots, block_keys, state)
    touched[s] = True
    return s


@njit(cache=True, inline="always")
def recent_slot(bx, by, bz, a, b):
    """Slot of block ``(bx, by, bz)`` when it is one of the two blocks looked up last (``a``,
    ``b``: ``(bx, by, bz, slot)``), else -1. Consecutive rays mostly cross the same two blocks,
    so most hash lookups are saved."""
    if bx == a[0] and by == a[1] and bz == a[2]:
        return a[3]
    if bx == b[0] and by == b[1] and bz == b[2]:
        return b[3]
    return -1
