"""Sparse TSDF: signed distances, weights, the active-region cap, sparse growth."""

from __future__ import annotations

import numpy as np
import pytest

from dm2.fusion.tsdf.field import SparseTSDF


def _plane_rays(n, z, rng, tilt=(0.0, -50.0, 80.0), extent=40.0):
    pts = np.column_stack([rng.uniform(0, extent, n), rng.uniform(0, extent, n), np.full(n, z)])
    return pts + np.asarray(tilt), pts


def _zero_crossing(tsdf, x, y):
    """Height [mm] of the zero crossing in the voxel column through (x, y)."""
    v = np.floor(np.array([x, y]) / tsdf.voxel_mm).astype(int)
    d, w = tsdf.dense(np.array([v[0], v[1], -40]), (1, 1, 80))
    d, w = d.ravel(), w.ravel()
    z = (np.arange(-40, 40) + 0.5) * tsdf.voxel_mm
    for k in range(79):
        if w[k] > 0 and w[k + 1] > 0 and d[k] < 0 <= d[k + 1]:
            return z[k] + (0 - d[k]) / (d[k + 1] - d[k]) * tsdf.voxel_mm
    raise AssertionError("no zero crossing")


def test_plane_is_recovered_with_the_right_sign():
    rng = np.random.default_rng(0)
    tsdf = SparseTSDF(0.5, 1.5, 8.0)
    o, p = _plane_rays(100_000, 2.3, rng)
    tsdf.integrate(o, p)
    for xy in [(10.2, 10.9), (20.7, 30.1), (33.3, 5.5)]:
        assert _zero_crossing(tsdf, *xy) == pytest.approx(2.3, abs=0.02)
    d, w = tsdf.sample(np.array([[20.0, 20.0, 3.3], [20.0, 20.0, 1.3]]))
    assert d[0] > 0 > d[1]  # positive in front of the surface (towards the sensor)
    assert w[0] > 0 and w[1] > 0


def test_weights_fall_off_behind_the_surface_in_the_active_region_too():
    rng = np.random.default_rng(1)
    o, p = _plane_rays(50_000, 0.0, rng, tilt=(0.0, 0.0, 80.0))
    # (the active weight cap out of the way: 1e6)
    inact, act = SparseTSDF(0.5, 1.5, 1e6), SparseTSDF(0.5, 1.5, 1e6)
    inact.integrate(o, p)
    act.integrate(o, p, np.ones(len(p), bool))
    z = np.array([[20.1, 20.1, 0.75], [20.1, 20.1, -0.75]])  # in front / behind by 0.75 mm
    _, wi = inact.sample(z)
    _, wa = act.sample(z)
    assert wi[1] == pytest.approx(0.5 * wi[0], rel=0.05)  # w_I = 1 - 0.75 / 1.5 behind
    assert wa[1] == pytest.approx(0.5 * wa[0], rel=0.05)  # w_A alike


def _topmost_crossing(tsdf, x, y):
    """Height [mm] of the topmost + over - zero crossing in the voxel column through (x, y)."""
    v = np.floor(np.array([x, y]) / tsdf.voxel_mm).astype(int)
    d, w = tsdf.dense(np.array([v[0], v[1], -10]), (1, 1, 20))
    d, w = d.ravel(), w.ravel()
    z = (np.arange(-10, 10) + 0.5) * tsdf.voxel_mm
    for k in range(18, -1, -1):
        if w[k] > 0 and w[k + 1] > 0 and d[k] < 0 <= d[k + 1]:
            return z[k] + (0 - d[k]) / (d[k + 1] - d[k]) * tsdf.voxel_mm
    raise AssertionError("no zero crossing")


def test_a_ray_grazing_a_rim_puts_no_surface_in_the_free_space_beyond():
    # a 1 mm step (x < 20 mm) seen from above, then the spray passes (the weights reset to one
    # observation) and a profile at 15 deg, one ray per voxel column, grazes the step's rim:
    # the rays' band behind the rim runs on into the free space over the lower plate, which
    # must stay free (at full weight behind, the column 1 mm past the rim read 0.79 mm)
    rng = np.random.default_rng(4)
    x, y = rng.uniform(0, 40, 40_000), rng.uniform(0, 40, 40_000)
    p = np.column_stack([x, y, np.where(x < 20.0, 1.0, 0.0)])
    tsdf = SparseTSDF(0.5, 1.5)
    for _ in range(4):
        tsdf.integrate(p + [0.0, 0.0, 80.0], p, np.ones(len(p), bool))
    tsdf.cap_weights_near_axis([20.0, 20.0, 0.0], [0.0, 0.0, -1.0], 30.0, 10.0, 1.0)
    ys = np.arange(5.25, 35.0, 0.5)
    rim = np.column_stack([np.full(ys.size, 19.8), ys, np.full(ys.size, 1.0)])
    ray = np.array([np.cos(np.radians(15.0)), 0.0, -np.sin(np.radians(15.0))])
    tsdf.integrate(rim - 60.0 * ray, rim, np.ones(len(rim), bool))
    for yy in (10.2, 20.2, 30.2):
        assert _topmost_crossing(tsdf, 20.8, yy) == pytest.approx(0.0, abs=0.1)
        assert _topmost_crossing(tsdf, 10.2, yy) == pytest.approx(1.0, abs=0.1)


def test_active_cap_follows_a_rise_while_uncapped_history_lags():
    rng = np.random.default_rng(2)
    capped, plain = SparseTSDF(0.5, 1.5, weight_cap=4.0), SparseTSDF(0.5, 1.5, weight_cap=4.0)
    for _ in range(20):  # long history on the old surface
        o, p = _plane_rays(20_000, 0.0, rng, tilt=(0.0, 0.0, 80.0))
        capped.integrate(o, p, np.ones(len(p), bool))
        plain.integrate(o, p)
    for _ in range(5):  # the surface rose by 1 mm
        o, p = _plane_rays(20_000, 1.0, rng, tilt=(0.0, 0.0, 80.0))
        capped.integrate(o, p, np.ones(len(p), bool))
        plain.integrate(o, p)
    assert _zero_crossing(capped, 20.2, 20.2) == pytest.approx(1.0, abs=0.1)
    assert _zero_crossing(plain, 20.2, 20.2) < 0.7  # inactive voxels keep their history


def test_blocks_are_allocated_only_near_observed_surfaces_and_growth_is_exact():
    rng = np.random.default_rng(3)
    o, p = _plane_rays(60_000, -3.7, rng)  # negative block coordinates as well
    small, big = SparseTSDF(0.5, 1.5, initial_blocks=64), SparseTSDF(0.5, 1.5,
                                                                    initial_blocks=4096)
    small.integrate(o, p)
    big.integrate(o, p)
    assert small.n_blocks == big.n_blocks
    # a 40 x 40 mm plane in 4 mm blocks, band +-1.5 mm: at most 11 x 11 x 2 blocks
    assert 100 <= small.n_blocks <= 11 * 11 * 3
    a = small.dense(np.array([0, 0, -12]), (80, 80, 8))
    b = big.dense(np.array([0, 0, -12]), (80, 80, 8))
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])
    assert small.block_coords()[:, 2].min() < 0


def test_bad_arguments_are_rejected():
    with pytest.raises(ValueError, match="voxel_mm"):
        SparseTSDF(voxel_mm=3.0)
    t = SparseTSDF()
    with pytest.raises(ValueError, match="must both be"):
        t.integrate(np.zeros((3, 3)), np.zeros((2, 3)))
