"""Batched fusion gives exactly the unbatched result; the one-pass kernel equals register+fuse."""

from __future__ import annotations

import numpy as np
import pytest
from test_monitor_scene import Scene, make_calibration, raster_run
from test_pipeline import _two_layers

from dm2.core.config import MonitorConfig, ProcessConfig
from dm2.core.messages import Profile, RobotState, Toolpath
from dm2.fusion.fusion import TsdfFusion
from dm2.fusion.registration import profile_frames, register_profiles, spot_B
from dm2.fusion.tsdf import field as tsdf_field
from dm2.fusion.tsdf.field import SparseTSDF


@pytest.fixture(scope="module")
def cal():
    return make_calibration()


def _toolpath():
    n = 12
    pos = np.array([[40 + 2 * i, 60, 0.0] for i in range(n)] +
                   [[62 - 2 * i, 60, 0.0] for i in range(n)] +
                   [[40 + 2 * i, 60, 0.8] for i in range(n)] +
                   [[62 - 2 * i, 60, 0.8] for i in range(n)])
    m = 4 * n
    return Toolpath(pos, np.tile([0, 0, -1.0], (m, 1)), np.full(m, 30.0), np.zeros(m),
                    np.repeat([0, 1], 2 * n), np.ones(m, bool), np.zeros(m))


def _run(cal, msgs, batch, toolpath=None, bounds=None):
    mon = TsdfFusion(cal, MonitorConfig(), ProcessConfig(), toolpath=toolpath, bounds_O=bounds,
                  batch_profiles=batch, max_delay_s=np.inf)
    mon.feed_all(msgs)
    mon.finish()
    return mon


def test_batch_size_never_changes_the_fused_field_or_the_layer_split(cal):
    msgs0, msgs1 = _two_layers(cal)
    msgs = msgs0 + msgs1
    bounds = ((44.0, 0.0, -10.0), (120.0, 120.0, 50.0))  # cuts through the profiles
    runs = [_run(cal, msgs, b, _toolpath(), bounds) for b in (1, 3, 7, 1000)]
    ref = runs[0]
    n = ref.tsdf.n_blocks
    assert n > 50 and ref.dropped["out_of_range"] > 1000
    assert [ls.layer for ls in ref.layer_done] == [0, 1]
    for mon in runs[1:]:
        assert mon.tsdf.n_blocks == n  # the same blocks (large batches: another slot order)
        ia, ib = np.argsort(mon.tsdf.block_keys[:n]), np.argsort(ref.tsdf.block_keys[:n])
        np.testing.assert_array_equal(mon.tsdf.block_keys[ia], ref.tsdf.block_keys[ib])
        np.testing.assert_array_equal(mon.tsdf.voxels[ia], ref.tsdf.voxels[ib])  # bit-exact
        assert (mon.points_fused, mon.profiles_fused, mon.dropped) == \
            (ref.points_fused, ref.profiles_fused, ref.dropped)
        # layer 0 closed at the same profile even when the change fell inside a batch
        for a, b in zip(mon.layer_done, ref.layer_done, strict=True):
            assert a.layer == b.layer and a.stamp_s == b.stamp_s
            np.testing.assert_array_equal(a.surface.vertices_O, b.surface.vertices_O)


def test_one_pass_kernel_equals_registration_then_ray_fusion(cal):
    msgs, _ = raster_run(Scene(boxes=[((50, 50, 0), (66, 66, 6))]), cal,
                            [((40, 58, 0), (80, 58, 0))], step_mm=2.0, noise_mm=0.05, seed=2)
    profiles = [m for m in msgs if isinstance(m, Profile)][:40]
    xz = np.concatenate([p.xz_S[p.valid] for p in profiles])
    offsets = np.concatenate([[0], np.cumsum([int(p.valid.sum()) for p in profiles])])
    sensors = list(cal.T_B_S)
    states = [m for m in msgs if isinstance(m, RobotState)]
    T_B_F = np.stack([states[4 * j].T_B_F for j in range(len(profiles))])  # along the raster
    T_O_S, spots, axes = profile_frames(
        T_B_F, cal.T_F_O, np.stack([cal.T_B_S[s] for s in sensors]),
        np.array([sensors.index(p.sensor_id) for p in profiles]),
        spot_B(cal, 30.0), cal.T_B_N[:3, 2].copy())
    one = SparseTSDF(0.5, 1.5, 4.0)
    fused, out = one.integrate_profiles(xz, offsets, T_O_S, spots, axes, 3.0)
    # the same in two steps: points in O, the active test in numpy, then ray fusion
    pts, origins = register_profiles(xz, offsets, T_O_S)
    counts = np.diff(offsets)
    q = pts - np.repeat(spots, counts, axis=0)
    ax = np.repeat(axes, counts, axis=0)
    along = q[:, 0] * ax[:, 0] + q[:, 1] * ax[:, 1] + q[:, 2] * ax[:, 2]
    active = (q[:, 0] * q[:, 0] + q[:, 1] * q[:, 1] + q[:, 2] * q[:, 2]) - along * along <= 9.0
    assert 0 < active.sum() < len(active)  # both regions are exercised
    two = SparseTSDF(0.5, 1.5, 4.0)
    two.integrate(origins, pts, active)
    assert (fused, out) == (len(xz), 0)
    n = two.n_blocks
    assert one.n_blocks == n
    np.testing.assert_array_equal(one.block_keys[:n], two.block_keys[:n])
    np.testing.assert_array_equal(one.voxels[:n], two.voxels[:n])
    # and the frames are the rigid inverse composed as written
    j = 5
    T_O_B = np.linalg.inv(T_B_F[j] @ cal.T_F_O)
    np.testing.assert_allclose(T_O_S[j], T_O_B @ cal.T_B_S[profiles[j].sensor_id], atol=1e-9)
    np.testing.assert_allclose(spots[j], T_O_B[:3, :3] @ spot_B(cal, 30.0) + T_O_B[:3, 3],
                               atol=1e-9)


def test_deposit_capped_batch_equals_cap_then_fuse_per_profile_with_growth(cal):
    msgs, _ = raster_run(Scene(boxes=[((50, 50, 0), (66, 66, 6))]), cal,
                         [((40, 58, 0), (80, 58, 0))], step_mm=2.0, noise_mm=0.05, seed=4)
    profiles = [m for m in msgs if isinstance(m, Profile)][:30] * 2  # seen twice: caps bite
    xz = np.concatenate([p.xz_S[p.valid] for p in profiles])
    offsets = np.concatenate([[0], np.cumsum([int(p.valid.sum()) for p in profiles])])
    sensors = list(cal.T_B_S)
    states = [m for m in msgs if isinstance(m, RobotState)]
    T_B_F = np.stack([states[4 * (j % 30)].T_B_F for j in range(len(profiles))])
    T_O_S, spots, axes = profile_frames(
        T_B_F, cal.T_F_O, np.stack([cal.T_B_S[s] for s in sensors]),
        np.array([sensors.index(p.sensor_id) for p in profiles]),
        spot_B(cal, 30.0), cal.T_B_N[:3, 2].copy())
    # the serial kernel (two threads give its voxels in another block order: test_tsdf_threads)
    one = SparseTSDF(0.5, 1.5, 4.0, initial_blocks=8, threads=1)  # grows many times in the call
    fused = one.integrate_profiles(xz, offsets, T_O_S, spots, axes, 3.0, deposit=(3.0, 3.0, 1.0))
    two = SparseTSDF(0.5, 1.5, 4.0, initial_blocks=8)
    capped, total = 0, [0, 0]
    for j in range(len(profiles)):
        capped += two.cap_weights_near_axis(spots[j], axes[j], 3.0, 3.0, 1.0)
        a, b = offsets[j], offsets[j + 1]
        got = two.integrate_profiles(xz[a:b], np.array([0, b - a]), T_O_S[j:j + 1],
                                     spots[j:j + 1], axes[j:j + 1], 3.0)
        total = [total[0] + got[0], total[1] + got[1]]
    assert capped > 1000  # the second sight of each place found weights to cap
    assert fused == tuple(total) and fused[0] == len(xz)
    n = two.n_blocks
    assert one.n_blocks == n > 8
    np.testing.assert_array_equal(one.block_keys[:n], two.block_keys[:n])
    np.testing.assert_array_equal(one.voxels[:n], two.voxels[:n])
    split = SparseTSDF(0.5, 1.5, 4.0, initial_blocks=8, threads=2)  # the batch is split
    assert len(xz) >= tsdf_field.MIN_SPLIT_POINTS
    assert split.integrate_profiles(xz, offsets, T_O_S, spots, axes, 3.0,
                                    deposit=(3.0, 3.0, 1.0)) == fused
    ia, ib = np.argsort(one.block_keys[:n]), np.argsort(split.block_keys[:n])
    np.testing.assert_array_equal(one.block_keys[:n][ia], split.block_keys[:n][ib])
    np.testing.assert_array_equal(one.voxels[:n][ia], split.voxels[:n][ib])


def test_integrate_profiles_rejects_mismatched_batches():
    tsdf = SparseTSDF(0.5, 1.5)
    with pytest.raises(ValueError, match="integrate_profiles"):
        tsdf.integrate_profiles(np.zeros((4, 2)), np.array([0, 3]), np.tile(np.eye(4), (1, 1, 1)),
                                np.zeros((1, 3)), np.zeros((1, 3)), 1.0)
