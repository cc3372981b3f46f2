"""Two-thread TSDF fusion gives the serial kernel's field bit for bit (block by block: the two
threads allocate blocks in another, deterministic, order)."""

from __future__ import annotations

import numpy as np
import pytest

from dm2.fusion.tsdf import field as tsdf_mod
from dm2.fusion.tsdf import kernels as K
from dm2.fusion.tsdf.field import SparseTSDF


def _assert_same_field(a: SparseTSDF, b: SparseTSDF) -> None:
    assert a.n_blocks == b.n_blocks
    n = a.n_blocks
    ia, ib = np.argsort(a.block_keys[:n]), np.argsort(b.block_keys[:n])
    assert np.array_equal(a.block_keys[ia], b.block_keys[ib])  # the same blocks
    assert np.array_equal(a.voxels[ia].view(np.uint32), b.voxels[ib].view(np.uint32))
    assert np.array_equal(a.touched[ia], b.touched[ib])
    for t in (a, b):  # the hash finds every block at its slot
        slots = [K.hash_find(t._table_keys, t._table_slots, key) for key in t.block_keys[:n]]
        assert np.array_equal(slots, np.arange(n))


def _sorted_rows(blocks: np.ndarray) -> np.ndarray:
    return blocks[np.lexsort(blocks.T[::-1])]


def _wavy_rays(n, rng):
    """Overlapping rays from three sensor directions onto a wavy surface (mm)."""
    x, y = rng.uniform(0, 40, n), rng.uniform(0, 40, n)
    pts = np.column_stack([x, y, 5 + np.sin(x / 3) + 0.05 * rng.standard_normal(n)])
    dirs = np.array([[0.0, -54.5, 77.8], [30.0, 20.0, 70.0], [-40.0, 10.0, 60.0]])
    return pts + dirs[rng.integers(0, 3, n)], pts, rng.random(n) < 0.3


def test_two_threads_equal_one_thread_bit_for_bit_on_overlapping_rays():
    rng = np.random.default_rng(7)
    o, p, act = _wavy_rays(300_000, rng)
    one = SparseTSDF(0.5, 1.5, 4.0, initial_blocks=64, threads=1)
    two = SparseTSDF(0.5, 1.5, 4.0, initial_blocks=64, threads=2)  # grows while planning
    for t in (one, two):
        for a in range(0, 300_000, 100_000):  # three passes over the same surface
            t.integrate(o[a:], p[a:], act[a:])
    assert one.n_blocks > 64 and (one.weight[: one.n_blocks] > 0).sum() > 30_000
    _assert_same_field(one, two)
    assert np.array_equal(_sorted_rows(one.take_touched()), _sorted_rows(two.take_touched()))


def _profiles_over_a_plane(rng, k=120, m=640):
    """``k`` profiles of ``m`` points, sensors moving along x over a plane: (xz_S, offsets,
    T_O_S, spot_O, axis_O, bounds_O)."""
    x = np.tile(np.linspace(-20.0, 20.0, m), k)
    z = 90.0 + 0.2 * rng.standard_normal(k * m)
    z[rng.random(k * m) < 0.01] = -1.0  # behind the sensor: skipped
    xz = np.column_stack([x, z])
    offsets = np.arange(k + 1, dtype=np.int64) * m
    T = np.tile(np.eye(4), (k, 1, 1))
    T[:, :3, :3] = np.array([[1.0, 0, 0], [0, -1.0, 0], [0, 0, -1.0]])  # looks down -z
    T[:, 0, 3] = 30.0 + 0.3 * np.arange(k)
    T[:, 1, 3] = 30.0 + 5.0 * (np.arange(k) % 3)
    T[:, 2, 3] = 95.0
    spot = T[:, :3, 3] - [0.0, 0.0, 95.0]
    axis = np.tile([0.0, 0.0, -1.0], (k, 1))
    bounds = (np.array([0.0, 0.0, -10.0]), np.array([60.0, 60.0, 20.0]))
    return xz, offsets, T, spot, axis, bounds


def test_two_threads_equal_one_thread_for_registered_profiles():
    profiles = _profiles_over_a_plane(np.random.default_rng(3))
    one = SparseTSDF(0.5, 1.5, 4.0, initial_blocks=64, threads=1)
    two = SparseTSDF(0.5, 1.5, 4.0, initial_blocks=64, threads=2)
    got = [t.integrate_profiles(*profiles[:5], 3.0, profiles[5]) for t in (one, two)]
    assert got[0] == got[1] and got[0][1] > 0
    _assert_same_field(one, two)


@pytest.mark.parametrize("staging_blocks", [None, 24])
def test_two_threads_cap_around_the_spray_axis_as_one_thread(staging_blocks, monkeypatch):
    """With the deposit cap (dm2.fusion.tsdf.deposit) each thread caps its own columns before
    each profile's points: the serial capped kernel's field bit for bit, also when the threads
    stop and resume mid-batch (a tight staging area) and across an empty profile."""
    from dm2.fusion.tsdf import threads as tsdf_split

    xz, offsets, T, spot, axis, bounds = _profiles_over_a_plane(np.random.default_rng(9))
    spot[:, 2] = 5.0  # on the plane
    offsets = np.insert(offsets, 40, offsets[40])  # profile 40 is empty
    T, spot, axis = (np.insert(a, 40, a[40], axis=0) for a in (T, spot, axis))
    deposit = (2.0, 2.0, 1.0)
    one, two, uncapped = (SparseTSDF(0.5, 1.5, 4.0, initial_blocks=64, threads=n)
                          for n in (1, 2, 1))
    resumed = []
    real = tsdf_split._timed_run

    def spy(tid, start, n, *args):
        resumed.append(0 < start < n)
        return real(tid, start, n, *args)

    monkeypatch.setattr(tsdf_split, "_timed_run", spy)
    if staging_blocks:
        two._split_buffers = tsdf_split.SplitBuffers(capacity=staging_blocks)
    for _ in range(2):  # the second pass meets the first pass's weights around the axis
        got = [t.integrate_profiles(xz, offsets, T, spot, axis, 3.0, bounds, deposit)
               for t in (one, two)]
        uncapped.integrate_profiles(xz, offsets, T, spot, axis, 3.0, bounds)
    assert got[0] == got[1] and got[0][1] > 0
    assert any(resumed) == bool(staging_blocks)  # the tight area made the threads resume
    _assert_same_field(one, two)
    n = one.n_blocks  # the cap did act: less weight than without it, the same blocks
    assert n == uncapped.n_blocks
    assert np.array_equal(one.block_keys[:n], uncapped.block_keys[:n])
    lower = one.weight[:n] < uncapped.weight[:n]
    assert lower.sum() > 200 and not (one.weight[:n] > uncapped.weight[:n]).any()


def test_small_batches_use_the_serial_kernel_and_threads_is_validated(monkeypatch):
    rng = np.random.default_rng(5)
    o, p, act = _wavy_rays(3000, rng)
    monkeypatch.setattr(tsdf_mod, "MIN_SPLIT_POINTS", 10**9)
    serial = SparseTSDF(0.5, 1.5, threads=2)
    serial.integrate(o, p, act)
    monkeypatch.setattr(tsdf_mod, "MIN_SPLIT_POINTS", 1)
    split = SparseTSDF(0.5, 1.5, threads=2)
    split.integrate(o, p, act)
    _assert_same_field(serial, split)
    with pytest.raises(ValueError, match="threads"):
        SparseTSDF(threads=3)


def test_full_staging_areas_commit_and_resume_with_the_same_field(monkeypatch):
    """When a thread's staging area fills up, its staged blocks are committed and it goes on
    from the ray where it stopped: still the serial kernel's field."""
    from dm2.fusion.tsdf import threads as tsdf_split

    rng = np.random.default_rng(11)
    o, p, act = _wavy_rays(40_000, rng)
    one = SparseTSDF(0.5, 1.5, 4.0, initial_blocks=64, threads=1)
    one.integrate(o, p, act)
    runs = []
    real = tsdf_split._timed_run

    def spy(tid, start, n, *args):
        runs.append((tid, start))
        return real(tid, start, n, *args)

    monkeypatch.setattr(tsdf_split, "_timed_run", spy)
    tight = SparseTSDF(0.5, 1.5, 4.0, initial_blocks=64, threads=2)
    tight._split_buffers = tsdf_split.SplitBuffers(capacity=24)  # 8 new blocks per run
    tight.integrate(o, p, act)
    assert one.n_blocks > 100 and len(runs) > 20  # many runs, resumed mid-batch
    assert any(start > 0 for _, start in runs)
    _assert_same_field(one, tight)
