"""Where the reference grows outside the spray's capped cylinder (a tall part's flanks, the
plate around its foot), the fused surface follows the growth instead of averaging it with its
history: the columns the reference grew in have their TSDF weights capped."""

from __future__ import annotations

import numpy as np
import pytest
from test_tsdf import _zero_crossing

from dm2.fusion.tsdf.field import SparseTSDF
from dm2.pipeline.grown_columns import GrownColumns

CELL_MM = 0.25


def _rays(n, z_of_x, rng, extent=40.0):
    """Vertical rays onto the surface ``z = z_of_x(x)`` over a square plate."""
    x, y = rng.uniform(0, extent, n), rng.uniform(0, extent, n)
    p = np.column_stack([x, y, z_of_x(x)])
    return p + np.array([0.0, 0.0, 80.0]), p


def _grow(with_caps: bool):
    """A flank (x < 20 mm) that grows 0.1 mm per pass for 30 passes, seen in 8 sweeps of 5,000
    rays per pass by inactive voxels (inactive cap 50, about 6 observations of a voxel column
    per pass); the plate beyond x = 20 mm does not grow. Returns the fused heights of the flank
    and of the plate, and the grown-columns cap."""
    rng = np.random.default_rng(7)
    tsdf = SparseTSDF(0.5, 1.5, weight_cap=8.0)
    n = int(40 / CELL_MM)
    heights = np.zeros((n, n))
    flank = (np.arange(n) + 0.5) * CELL_MM < 20.0
    grown = GrownColumns(heights.shape, CELL_MM, tsdf, 1.0 if with_caps else None)
    for k in range(30):
        rise = 0.1 * (k + 1)
        heights[:, flank] = rise  # the reference after this pass
        grown.update(heights)
        for _ in range(8):
            o, p = _rays(5_000, lambda x, r=rise: np.where(x < 20.0, r, 0.0), rng)
            tsdf.integrate(o, p)
    return _zero_crossing(tsdf, 10.2, 20.2), _zero_crossing(tsdf, 30.2, 20.2), grown


def test_a_growing_flank_is_followed_where_its_history_would_lag():
    flank_mm, plate_mm, grown = _grow(with_caps=True)
    assert flank_mm == pytest.approx(3.0, abs=0.1)  # the true flank after 30 passes
    assert plate_mm == pytest.approx(0.0, abs=0.05)
    assert grown.capped_voxels > 0
    lagging_mm, plate_plain_mm, plain = _grow(with_caps=False)
    assert lagging_mm < 2.0 and plain.capped_voxels == 0  # the mean of 50 observations lags
    assert plate_plain_mm == pytest.approx(0.0, abs=0.05)


def test_only_grown_columns_are_capped_and_distances_are_kept():
    rng = np.random.default_rng(3)
    tsdf = SparseTSDF(0.5, 1.5)
    for _ in range(10):
        o, p = _rays(20_000, lambda x: np.zeros_like(x), rng)
        tsdf.integrate(o, p)
    before_d, before_w = tsdf.dense(np.array([0, 0, -4]), (80, 80, 8))
    heights = np.zeros((160, 160))
    heights[40:48, 40:48] = 0.3  # 2 x 2 mm at (10-12, 10-12) mm grew 0.3 mm
    heights[100:104, 100:104] = 0.2  # less than half a voxel: not stale yet
    grown = GrownColumns(heights.shape, CELL_MM, tsdf, 1.0)
    grown.update(heights)
    d, w = tsdf.dense(np.array([0, 0, -4]), (80, 80, 8))
    np.testing.assert_array_equal(d, before_d)  # signed distances untouched
    changed = w != before_w
    cols = np.argwhere(changed.any(axis=2))
    assert set(map(tuple, cols)) == {(i, j) for i in range(20, 24) for j in range(20, 24)}
    assert np.all(w[changed] == 1.0)
    # the next update caps only what grew since: the small growth, now past half a voxel
    heights[100:104, 100:104] = 0.6
    grown.update(heights)
    w2 = tsdf.dense(np.array([0, 0, -4]), (80, 80, 8))[1]
    cols2 = np.argwhere((w2 != w).any(axis=2))
    assert set(map(tuple, cols2)) == {(i, j) for i in range(50, 52) for j in range(50, 52)}
