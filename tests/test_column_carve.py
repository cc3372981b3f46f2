"""A spot the profilers see only at grazing angles keeps, under its new top, the free space of
its old tops: where the reference grew, such enclosed stale free slabs are carved into inferred
material at the layer mark; a dent (nothing observed above its floor) and free space seen again
since the column's last cap are kept."""

from __future__ import annotations

import numpy as np
import pytest

from dm2.fusion.tsdf import kernels as K
from dm2.fusion.tsdf.carve import CARVE_RUN_VOXELS, CARVE_WEIGHT
from dm2.fusion.tsdf.field import SparseTSDF
from dm2.pipeline.grown_columns import GrownColumns

CELL_MM = 0.25
EXTENT_MM = 60.0


def _vertical(tsdf, rng, x_lo, x_hi, z_mm, n=30_000):
    """Vertical rays onto the plane ``z = z_mm`` over ``x_lo <= x < x_hi``, all y."""
    x, y = rng.uniform(x_lo, x_hi, n), rng.uniform(0, EXTENT_MM, n)
    p = np.column_stack([x, y, np.full(n, z_mm)])
    tsdf.integrate(p + np.array([0.0, 0.0, 80.0]), p)


def _crossings(tsdf, x, y, min_weight=1.0):
    """Heights [mm] of every zero crossing (material below, free above) of the column at (x, y)
    between voxels both at ``min_weight`` or more (what the surface extraction meshes)."""
    v = np.floor(np.array([x, y]) / tsdf.voxel_mm).astype(int)
    d, w = tsdf.dense(np.array([v[0], v[1], -8]), (1, 1, 40))
    d, w = d.ravel(), w.ravel()
    z = (np.arange(-8, 32) + 0.5) * tsdf.voxel_mm
    return [float(z[k] - d[k] / (d[k + 1] - d[k]) * tsdf.voxel_mm) for k in range(39)
            if w[k] >= min_weight and w[k + 1] >= min_weight and d[k] < 0 <= d[k + 1]]


def _build():
    """Three strips of a plate whose top was seen at 2 mm; the reference then grows to 5 mm.
    Buried (x < 20): the new top at 5 mm is seen, the old band's free space 2-3.5 mm is not.
    Dent (20-40): only the old floor at 2 mm is seen again, nothing above it. Seen again (40+):
    the new top is seen, and the old top's free space is seen again too."""
    rng = np.random.default_rng(11)
    tsdf = SparseTSDF(0.5, 1.5, weight_cap=8.0)
    _vertical(tsdf, rng, 0, EXTENT_MM, 2.0, 60_000)
    n = int(EXTENT_MM / CELL_MM)
    heights = np.full((n, n), 2.0)
    grown = GrownColumns(heights.shape, CELL_MM, tsdf, 1.0)
    grown.calibrated(heights, 2.0, 1.0)  # the columns count their growth from 2 mm
    heights[:] = 5.0
    grown.update(heights)  # caps 0.5-6.5 mm at weight 1; nothing is enclosed yet
    assert grown.carved_voxels == 0
    _vertical(tsdf, rng, 0, 20, 5.0)
    _vertical(tsdf, rng, 20, 40, 2.0)
    _vertical(tsdf, rng, 40, EXTENT_MM, 5.0)
    _vertical(tsdf, rng, 40, EXTENT_MM, 2.0, 120_000)  # every column seen again (25 rays each)
    return tsdf, heights, grown


def test_a_buried_old_top_is_carved_and_a_dent_is_kept():
    tsdf, heights, grown = _build()
    buried, dent, again = (10.1, 30.1), (30.1, 30.1), (50.1, 30.1)
    assert _crossings(tsdf, *buried) == [pytest.approx(2.0, abs=0.02),
                                         pytest.approx(5.0, abs=0.02)]
    v = np.floor(np.array(dent) / tsdf.voxel_mm).astype(int)
    dent_before = tsdf.dense(np.array([v[0], v[1], -8]), (1, 1, 40))
    again_before = _crossings(tsdf, *again)
    heights[:] = 5.5  # the next layer mark
    grown.update(heights)
    assert grown.carved_voxels > 0
    assert _crossings(tsdf, *buried) == [pytest.approx(5.0, abs=0.02)]
    # the carved slab is inferred material, below min_weight
    vb = np.floor(np.array(buried) / tsdf.voxel_mm).astype(int)
    d, w = tsdf.dense(np.array([vb[0], vb[1], 4]), (1, 1, 3))  # 2.0-3.5 mm
    np.testing.assert_array_equal(d.ravel(), -1.5)
    np.testing.assert_array_equal(w.ravel(), CARVE_WEIGHT)
    # the dent's column is bit for bit what it was, but for the cap above its floor
    dent_after = tsdf.dense(np.array([v[0], v[1], -8]), (1, 1, 40))
    np.testing.assert_array_equal(dent_after[0], dent_before[0])
    assert _crossings(tsdf, *dent) == [pytest.approx(2.0, abs=0.02)]
    # free space seen again since the cap is measurement, not stale: both surfaces are kept
    assert again_before == _crossings(tsdf, *again) and len(again_before) == 2
    # carved columns: only the buried strip's
    carved = _carved_columns(tsdf)
    assert carved and all(x < 20.0 for x, _ in carved)


def _carved_columns(tsdf):
    d, w = tsdf.dense(np.array([0, 0, -8]), (120, 120, 40))
    cols = np.argwhere(((w == CARVE_WEIGHT) & (d == -tsdf.truncation_mm)).any(axis=2))
    return [((i + 0.5) * tsdf.voxel_mm, (j + 0.5) * tsdf.voxel_mm) for i, j in cols]


def _carve_oracle(d, w, stale_below, truncation_mm):
    """The rule in plain Python on one column ``d, w (nz,)`` walked from the top down; returns
    the carved column and the number of voxels carved."""
    d, w = d.copy(), w.copy()
    above, run, n = False, [], 0
    for k in range(len(d) - 1, -1, -1):
        if w[k] <= 0 or d[k] > 0:  # unobserved or free
            if above and w[k] < stale_below and run is not None and len(run) < CARVE_RUN_VOXELS:
                run.append(k)
            else:
                run = None
        else:
            for j in run or []:
                d[j], w[j] = -truncation_mm, CARVE_WEIGHT
            n += len(run or [])
            run, above = [], True
    return d, w, n


def test_the_column_carve_equals_its_plain_statement_bit_for_bit():
    rng = np.random.default_rng(5)
    tsdf = SparseTSDF(0.5, 1.5, weight_cap=8.0)
    for z in (1.0, 4.0, 7.0, 10.0, 13.0, 16.0, 19.0):  # allocate the blocks of 0-20 mm
        _vertical(tsdf, rng, 0, 8, z, 4_000)
    nz = 40
    d0, w0 = tsdf.dense(np.array([0, 0, 0]), (16, 16, nz))
    # random stacks of material, free and unobserved voxels, stale or seen again
    d = rng.choice([-0.7, -0.1, 0.0, 0.2, 1.1], size=d0.shape).astype(np.float32)
    w = rng.choice([0.0, 0.5, 1.0, 1.0, 1.0, 2.0], size=w0.shape).astype(np.float32)
    d[:, :, 5:] = np.where(rng.random(d[:, :, 5:].shape) < 0.6, 0.4, d[:, :, 5:])  # long runs
    for i in range(16):
        for j in range(16):
            for k in range(nz):
                s = K.hash_find(tsdf._table_keys, tsdf._table_slots,
                                K.pack_key(i >> 3, j >> 3, k >> 3))
                assert s >= 0
                li = (i & 7) + 8 * ((j & 7) + 8 * (k & 7))
                tsdf.voxels[s, li, 0], tsdf.voxels[s, li, 1] = d[i, j, k], w[i, j, k]
    xy = np.array([[(i + 0.5) * 0.5, (j + 0.5) * 0.5] for i in range(16) for j in range(16)])
    n = tsdf.carve_buried_in_columns(xy, np.full(len(xy), 0.1), np.full(len(xy), 19.9), 2.0)
    d1, w1 = tsdf.dense(np.array([0, 0, 0]), (16, 16, nz))
    expected = 0
    for i in range(16):
        for j in range(16):
            de, we, ne = _carve_oracle(d[i, j], w[i, j], 2.0, 1.5)
            np.testing.assert_array_equal(d1[i, j], de)
            np.testing.assert_array_equal(w1[i, j], we)
            expected += ne
    assert n == expected > 50


def test_unobserved_voxels_inside_an_enclosed_stale_slab_are_carved_with_it():
    """Material seen up to 2 mm and, after growth, a new top band at 6 mm; between them stale
    free voxels with a gap no ray reached (weight 0): the whole slab is buried material. The
    same column with nothing observed above the gap (a dent) and with a free voxel of the slab
    seen again since the cap are kept as they are."""
    rng = np.random.default_rng(9)
    tsdf = SparseTSDF(0.5, 1.5, weight_cap=8.0)
    for z in (1.0, 4.0, 7.0):  # allocate the blocks of 0-8 mm
        _vertical(tsdf, rng, 0, 8, z, 4_000)
    nz = 16
    # voxel k holds 0.5 k - 0.5 (k + 1) mm: material to 2 mm, free 2-3, gap 3-4, free 4-5.5,
    # the new top's band 5.5-6.5, free above
    col = np.array([-1.0, -0.8, -0.6, -0.4, 0.3, 0.8, 0.0, 0.0, 1.2, 1.5, 1.5, -1.2, -0.3,
                    0.2, 0.7, 1.5], np.float32)
    wts = np.array([1, 1, 1, 1, 1, 1, 0, 0, 1, 1, 1, 4, 6, 6, 5, 3], np.float32)
    dent, dent_w = col.copy(), wts.copy()
    dent[11:], dent_w[11:] = 0.0, 0.0  # nothing observed above the gap
    seen = wts.copy()
    seen[8] = 3.0  # a free voxel of the slab seen again since the cap
    columns = {0: (col, wts), 2: (dent, dent_w), 4: (col, seen)}
    for i, (dc, wc) in columns.items():
        for k in range(nz):
            s = K.hash_find(tsdf._table_keys, tsdf._table_slots, K.pack_key(0, 0, k >> 3))
            li = i + 8 * (0 + 8 * (k & 7))
            tsdf.voxels[s, li, 0], tsdf.voxels[s, li, 1] = dc[k], wc[k]
    xy = np.array([[(i + 0.5) * 0.5, 0.25] for i in columns])
    n = tsdf.carve_buried_in_columns(xy, np.zeros(3), np.full(3, 7.9), 2.0)
    assert n == 7  # 2.0-5.5 mm of the first column: free, the gap, free
    d, w = tsdf.dense(np.array([0, 0, 0]), (5, 1, nz))
    np.testing.assert_array_equal(d[0, 0, 4:11], -1.5)
    np.testing.assert_array_equal(w[0, 0, 4:11], CARVE_WEIGHT)
    np.testing.assert_array_equal(d[0, 0, :4], col[:4])
    np.testing.assert_array_equal(d[0, 0, 11:], col[11:])
    for i, (dc, wc) in ((2, (dent, dent_w)), (4, (col, seen))):
        observed = wc > 0  # unobserved voxels read back as +truncation
        np.testing.assert_array_equal(d[i, 0][observed], dc[observed])
        np.testing.assert_array_equal(w[i, 0], wc)


def test_at_the_stream_end_the_buried_slab_is_carved_and_nothing_is_capped():
    """``update(cap=False)`` (the session's finish, before the last layer closes) carves the
    same slab as a layer mark would, leaves every other voxel as it was, and leaves the columns'
    growth to count from their last cap."""
    tsdf, heights, grown = _build()
    buried, again = (10.1, 30.1), (50.1, 30.1)
    before_d, before_w = tsdf.dense(np.array([0, 0, -8]), (120, 120, 40))
    capped_before = grown.capped_mm.copy()
    heights[:] = 5.5
    grown.update(heights, cap=False)
    assert grown.carved_voxels > 0
    assert _crossings(tsdf, *buried) == [pytest.approx(5.0, abs=0.02)]
    d, w = tsdf.dense(np.array([0, 0, -8]), (120, 120, 40))
    changed = (d != before_d) | (w != before_w)
    assert np.all((w[changed] == CARVE_WEIGHT) & (d[changed] == -tsdf.truncation_mm))
    assert {(i, j) for i, j in np.argwhere(changed.any(axis=2))} == \
        {(int(x / tsdf.voxel_mm), int(y / tsdf.voxel_mm)) for x, y in _carved_columns(tsdf)}
    assert len(_crossings(tsdf, *again)) == 2  # seen again: kept, and not capped
    np.testing.assert_array_equal(grown.capped_mm, capped_before)
