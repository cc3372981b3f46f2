"""Two-thread fusion of a batch into a :class:`~dm2.fusion.tsdf.field.SparseTSDF`; every voxel
bit-identical
to the serial kernel (:func:`dm2.fusion.tsdf.kernels.fuse_profiles` / ``integrate_rays``).

The calling thread and one pool thread each run :func:`dm2.fusion.tsdf.owned_kernels.fuse_owned`
over
the whole batch: each registers every point, skips the rays that lie in the other thread's block
columns and updates its own voxels. Blocks that are not allocated yet are staged per thread (in
rows of the voxel array reserved for it) and committed serially after the run
(:func:`dm2.fusion.tsdf.owned_kernels.commit_staged`); should a staging area fill up, its thread
stops
at a ray, the staged blocks are committed and that thread goes on from there. The kernels release
the GIL, so the two threads run on two cores at once.
"""

from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from dm2.fusion.tsdf import owned_kernels as OK
from dm2.fusion.tsdf.bundles import BlockHash, new_staging
from dm2.fusion.tsdf.carve import COL_SHIFT  # the checkerboard of block columns in x, y

STAGING_BLOCKS = 1024  # blocks a thread may stage per run before its staged blocks are committed
_POOL: ThreadPoolExecutor | None = None


def _pool() -> ThreadPoolExecutor:
    global _POOL
    if _POOL is None:
        _POOL = ThreadPoolExecutor(max_workers=1, thread_name_prefix="tsdf-fuse")
    return _POOL


class SplitBuffers:
    """The two threads' staging areas, reused across batches."""

    def __init__(self, capacity: int = STAGING_BLOCKS):
        self.capacity = int(capacity)
        self.staging = (new_staging(self.capacity), new_staging(self.capacity))


NO_DEPOSIT = (0.0, 0.0, 0.0)  # fuse_owned's deposit argument: no cap around the spray axis


def fuse_split(field, register: bool, use_bounds: bool, batch, params, counts,
               deposit: tuple = NO_DEPOSIT) -> None:
    """Fuse one batch into ``field`` with two threads (``batch``: a
    :class:`~dm2.fusion.tsdf.bundles.Batch`, ``params``: the
    :class:`~dm2.fusion.tsdf.bundles.FusionParams`, the flags as in
    :func:`dm2.fusion.tsdf.kernels.fuse_profiles`; ``deposit``: the cap around each profile's
    spray axis, as in :func:`dm2.fusion.tsdf.owned_kernels.fuse_owned`); ``counts`` (skipped,
    fused) is added to and ``field.split_cpu_s`` receives the phases' CPU seconds."""
    n = batch.xz_S.shape[0]
    buffers = field._split_buffers
    staging = buffers.staging
    starts = [0, 0]
    # each thread counts into its own cache line (a shared line would bounce between the
    # cores at every point); thread 0's counts are the batch's, as the serial kernel counts
    lines = np.zeros((2, 16), dtype=np.int64)
    while starts[0] < n or starts[1] < n:
        # rows for the blocks each thread may stage, beyond the allocated ones
        field._grow(2 * buffers.capacity)
        bases = (field.n_blocks, field.n_blocks + buffers.capacity)
        table = BlockHash(field._table_keys, field._table_slots)
        args = (register, use_bounds, batch, params, deposit, table, field.voxels, field.touched)
        other = _pool().submit(_timed_run, 1, starts[1], n, args, lines[1], bases[1],
                               staging[1])
        stop0, cpu0 = _timed_run(0, starts[0], n, args, lines[0], bases[0], staging[0])
        stop1, cpu1 = other.result()
        c0 = time.thread_time()
        for st, base in zip(staging, bases, strict=True):  # thread 0's first: fixed slots
            OK.commit_staged(st, base, table, field.block_keys, field.voxels, field.touched,
                             field._state)
        starts = [stop0, stop1]
        field.split_cpu_s += (time.thread_time() - c0, cpu0, cpu1, max(cpu0, cpu1))
    counts += lines[0, :2]


def _timed_run(tid: int, start: int, n: int, args: tuple, counts, base: int,
               st) -> tuple[int, float]:
    """``fuse_owned`` of thread ``tid`` from point ``start``: where it stopped and the CPU
    seconds it took on its thread."""
    if start >= n:
        return n, 0.0
    c = time.thread_time()
    register, use_bounds, batch, params, deposit, table, voxels, touched = args
    stop = OK.fuse_owned(tid, COL_SHIFT, start, register, use_bounds, batch, params, deposit,
                         table, voxels, touched, counts, base, st)
    return stop, time.thread_time() - c
