"""Two-thread fusion of a batch into a :class:`~dm2.tsdf.SparseTSDF`, bit-identical to the serial
kernel (:func:`dm2.tsdf_kernels.fuse_profiles` / ``integrate_rays``).

Three phases per batch, on the calling thread and one pool thread:

1. plan (both threads, half of the points each, :func:`dm2.tsdf_plan_kernels.plan_rays`): rays,
   active flags, column owners and the blocks the rays reach that are not allocated yet;
2. allocate (serial, :func:`dm2.tsdf_plan_kernels.alloc_listed`): those blocks in the serial
   kernel's order, growing the field where needed;
3. update (both threads, :func:`dm2.tsdf_split_kernels.update_rays`): each thread updates the
   voxels of its own block columns.

The kernels release the GIL, so the two threads run on two cores at once.
"""

from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from dm2 import tsdf_plan_kernels as PK
from dm2 import tsdf_split_kernels as SK

# Block columns of 2**COL_SHIFT blocks are dealt to the two threads as a checkerboard in x, y.
COL_SHIFT = 2
LIST_MARGIN = 64  # spare entries of a planning thread's list of missing blocks
_POOL: ThreadPoolExecutor | None = None


def _pool() -> ThreadPoolExecutor:
    global _POOL
    if _POOL is None:
        _POOL = ThreadPoolExecutor(max_workers=1, thread_name_prefix="tsdf-fuse")
    return _POOL


class SplitBuffers:
    """Scratch arrays reused across batches: ``ray_f (n, 7)``, ``ray_flags (n,)`` and each
    planning thread's list of missing block keys ``(2, n // 2 + LIST_MARGIN)``."""

    def __init__(self):
        self.ray_f = np.empty((0, 7))
        self.ray_flags = np.empty(0, dtype=np.uint8)
        self.new_keys = np.empty((2, 0), dtype=np.int64)

    def take(self, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        if self.ray_flags.shape[0] < n:
            self.ray_f = np.empty((n, 7))
            self.ray_flags = np.empty(n, dtype=np.uint8)
        if self.new_keys.shape[1] < n - n // 2 + LIST_MARGIN:
            self.new_keys = np.empty((2, n - n // 2 + LIST_MARGIN), dtype=np.int64)
        return self.ray_f[:n], self.ray_flags[:n], self.new_keys


def fuse_split(field, register, o, p, a, xz, off, T, spot, axis, r2, lo, hi, use_bounds,
               counts, max_weight: float) -> None:
    """Fuse one batch into ``field`` with two threads (arguments as in
    :func:`dm2.tsdf_kernels._fuse`); ``counts`` (skipped, fused) is added to and
    ``field.split_cpu_s`` receives the phases' CPU seconds."""
    n = xz.shape[0]
    ray_f, flags, new_keys = field._split_buffers.take(n)
    half = n // 2
    plan = (register, o, p, a, xz, off, T, spot, axis, r2, lo, hi, use_bounds)
    grid = (field.voxel_mm, field.truncation_mm, COL_SHIFT, field._table_keys,
            field._table_slots)
    counts1 = np.zeros(2, dtype=np.int64)
    ranges = ((0, half), (half, n))
    lists = [(new_keys[tid, : stop - start + LIST_MARGIN], np.zeros(2, dtype=np.int64))
             for tid, (start, stop) in enumerate(ranges)]
    other = _pool().submit(_timed_plan, plan + ranges[1] + grid + (counts1, ray_f, flags)
                           + lists[1])
    plan0 = _timed_plan(plan + ranges[0] + grid + (counts, ray_f, flags) + lists[0])
    plan1 = other.result()
    counts += counts1
    c0 = time.thread_time()
    for (keys, listed), (_, stop) in zip(lists, ranges, strict=True):
        j, n_keys = 0, int(listed[0])
        while j < n_keys:  # the listed blocks, in the serial kernel's order
            j = PK.alloc_listed(keys, n_keys, j, field._table_keys, field._table_slots,
                                field.block_keys, field._state)
            if j < n_keys:
                field._grow()
        i = int(listed[1])
        while i < stop:  # rays past a full list: walked in stream order
            i = PK.alloc_rays(ray_f, flags, i, stop, field.voxel_mm, field.truncation_mm,
                              field._table_keys, field._table_slots, field.block_keys,
                              field._state)
            if i < stop:
                field._grow()
    args = (COL_SHIFT, ray_f, flags, field.voxel_mm, field.truncation_mm, field.weight_cap,
            max_weight, field._table_keys, field._table_slots, field.voxels, field.touched)
    c1 = time.thread_time()
    other = _pool().submit(_timed_update, 1, args)
    missing0, cpu0 = _timed_update(0, args)
    missing1, cpu1 = other.result()
    field.split_cpu_s += (c1 - c0, plan0 + cpu0, plan1 + cpu1,
                          max(plan0, plan1) + max(cpu0, cpu1))
    missing = missing0 + missing1
    if missing:
        raise RuntimeError(f"SparseTSDF: {missing} voxel visits found no block "
                           "(the allocation plan missed a block)")


def _timed_plan(args: tuple) -> float:
    """``plan_rays`` of one half of the rays; the CPU seconds it took on its thread."""
    c = time.thread_time()
    PK.plan_rays(*args)
    return time.thread_time() - c


def _timed_update(tid: int, args: tuple) -> tuple[int, float]:
    """``update_rays`` of thread ``tid`` and the CPU seconds it took on its thread."""
    c = time.thread_time()
    missing = SK.update_rays(tid, *args)
    return missing, time.thread_time() - c
