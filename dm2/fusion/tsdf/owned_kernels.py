"""Kernels of the two-thread TSDF fusion (:mod:`dm2.fusion.tsdf.threads`): block columns owned by
threads.

The voxels are dealt to the two threads by a checkerboard of block columns in ``x, y``
(``2**col_shift`` blocks wide). :func:`fuse_owned` (``nogil``, one call per thread) walks every
ray of the batch that reaches its thread's columns with the serial kernel's own walk
(:func:`dm2.fusion.tsdf.walk.fuse_batch`, ``owned``) and updates only that thread's voxels. So
every voxel is updated by exactly one thread, in ray order, as the serial kernel updates it: the
fused field is the serial one bit for bit, whatever the thread timing.

The field's block table is only read while the threads run. A block a thread needs that is not
allocated yet goes into that thread's own staging area (keys and a small hash table) and its
voxels into rows of the field's voxel array reserved for that thread beyond the allocated
blocks; :func:`commit_staged` then allocates the staged blocks in the field, thread 0's before
thread 1's, each in the order its thread first reached them, moving their voxels down. Block
slots are therefore deterministic, though not in the serial kernel's order.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from dm2.fusion.tsdf.block_hash import hash_get_or_insert
from dm2.fusion.tsdf.bundles import StagedRows
from dm2.fusion.tsdf.walk import fuse_batch


class Staging:
    """One thread's blocks allocated during a run: ``keys (capacity,)`` int64 in allocation
    order, their hash (``table_keys``/``table_slots``, twice the capacity, a power of two) and
    ``state`` (``state[0]``: blocks staged). The staged blocks' voxels live in the field's own
    voxel array, in rows reserved for the thread (``base + s`` for staged block ``s``)."""

    def __init__(self, capacity: int = 1024):
        self.capacity = int(capacity)
        self.keys = np.full(capacity, -1, dtype=np.int64)
        self.table_keys = np.full(2 * capacity, -1, dtype=np.int64)
        self.table_slots = np.full(2 * capacity, -1, dtype=np.int32)
        self.state = np.zeros(1, dtype=np.int64)

    def rows(self, base: int) -> StagedRows:
        """The staging area with its reserved rows from ``base``, as the kernels take it."""
        return StagedRows(int(base), self.keys, self.table_keys, self.table_slots, self.state)


@njit(cache=True, nogil=True, error_model="numpy")
def fuse_owned(tid, col_shift, start, register, use_bounds, batch, params, blocks, counts,
               staged):
    """Thread ``tid`` (0 or 1): fuse its own voxels of the points from ``start`` on (arguments
    as in :func:`dm2.fusion.tsdf.kernels.fuse_profiles`; ``counts`` as the serial kernel counts
    the points walked). Blocks the field lacks are staged in rows ``staged.base:staged.base +
    len(staged.keys)`` of ``blocks.voxels`` (zero). Returns the index of the first point not
    handled because the staging area is full (the batch's length when done)."""
    if not register:  # literal flags: each variant is compiled without the other's tests
        return fuse_batch(True, False, False, tid, col_shift, start, batch, params, blocks,
                          staged, counts)
    if use_bounds:
        return fuse_batch(True, True, True, tid, col_shift, start, batch, params, blocks,
                          staged, counts)
    return fuse_batch(True, True, False, tid, col_shift, start, batch, params, blocks, staged,
                      counts)


@njit(cache=True)
def commit_staged(staged, blocks):
    """Serial: give a thread's staged blocks the next field slots in staging order (their
    voxels move down from the thread's reserved rows, which are zeroed again), mark them
    touched, and empty the staging area. The caller makes room first."""
    base, voxels = staged.base, blocks.voxels
    for j in range(staged.state[0]):
        s = hash_get_or_insert(staged.keys[j], blocks.table_keys, blocks.table_slots,
                               blocks.block_keys, blocks.state)
        if s != base + j:
            voxels[s, :, :] = voxels[base + j, :, :]
            voxels[base + j, :, :] = 0.0
        blocks.touched[s] = True
        staged.keys[j] = -1
    staged.table_keys[:] = -1
    staged.state[0] = 0
