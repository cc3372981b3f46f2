"""A surface buried by new material is carved away by active rays (deposition), kept by
inactive ones; the two-thread update carves the same voxels as one thread; a surface outside
the active region follows a rise within the inactive weight window."""

from __future__ import annotations

import numpy as np

from dm2.defects.realtime_kernels import column_crossings_weights
from dm2.fusion.tsdf.carve import CARVE_WEIGHT
from dm2.fusion.tsdf.field import SparseTSDF
from tests.test_tsdf_threads import _assert_same_field

# 55 degrees elevation, like the cell's profilers: the band (1.5 mm along the ray) reaches
# 1.23 mm below a new surface, less than the 1.6 mm the plane rises here
DIRECTION = np.array([0.0, -np.cos(np.radians(55.0)), np.sin(np.radians(55.0))])


def _plane_rays(z_mm: float, n: int, rng):
    x, y = rng.uniform(5, 35, n), rng.uniform(5, 35, n)
    pts = np.column_stack([x, y, np.full(n, z_mm) + 0.02 * rng.standard_normal(n)])
    return pts + 95.0 * DIRECTION, pts


def _crossings_mm(tsdf: SparseTSDF, x_mm: float, y_mm: float) -> list[float]:
    """Heights [mm] of the zero crossings of the column at (x, y) between observed voxels."""
    v = int(np.floor(x_mm / tsdf.voxel_mm)), int(np.floor(y_mm / tsdf.voxel_mm))
    d, w = tsdf.dense(np.array([v[0], v[1], -8]), (1, 1, 16))
    d, w = d[0, 0], w[0, 0]
    out = []
    for k in range(15):
        if w[k] > 0 and w[k + 1] > 0 and (d[k] > 0) != (d[k + 1] > 0):
            z0 = (k - 8 + 0.5) * tsdf.voxel_mm
            out.append(z0 + tsdf.voxel_mm * d[k] / (d[k] - d[k + 1]))
    return out


def _build(active_second: bool, threads: int) -> SparseTSDF:
    rng = np.random.default_rng(4)
    tsdf = SparseTSDF(0.5, 1.5, 8.0, threads=threads)
    for z, act in ((0.0, True), (1.6, active_second)):
        o, p = _plane_rays(z, 200_000, rng)
        tsdf.integrate(o, p, np.full(len(p), act))
    return tsdf


def test_active_rays_carve_the_buried_surface_inactive_rays_keep_it():
    for x, y in ((15.2, 20.3), (24.7, 12.9), (20.1, 26.6)):
        carved = _crossings_mm(_build(True, 1), x, y)
        assert len(carved) == 1 and abs(carved[0] - 1.6) < 0.1  # only the new top
        kept = _crossings_mm(_build(False, 1), x, y)
        assert len(kept) == 3  # the new top and both faces of the buried free-space slab
        assert max(kept) > 1.3 and min(kept) < 0.3  # (the top lags: inactive weights average)


def test_two_threads_carve_the_same_voxels_as_one():
    one, two = _build(True, 1), _build(True, 2)
    _assert_same_field(one, two)


def _grid_rays(z_mm: float):
    x, y = np.meshgrid(np.arange(10, 30, 0.5) + 0.13, np.arange(10, 30, 0.5) + 0.29)
    pts = np.column_stack([x.ravel(), y.ravel(), np.full(x.size, z_mm)])
    return pts + 95.0 * DIRECTION, pts


def _inactive_top_after_rise(inactive_weight_cap) -> float:
    tsdf = SparseTSDF(0.5, 1.5, 8.0, threads=1, inactive_weight_cap=inactive_weight_cap)
    for z in (0.0, 0.5):  # a surface outside the active region rises by one voxel
        o, p = _grid_rays(z)
        for _ in range(150):
            tsdf.integrate(o, p, np.zeros(len(p), bool))
    return _crossings_mm(tsdf, 20.1, 20.2)[-1]


def test_inactive_surface_follows_a_rise_within_the_weight_window():
    assert abs(_inactive_top_after_rise(None) - 0.5) < 0.05  # default window: 50 observations
    # weights let to grow to 1e4 average the whole history: the surface stays far behind
    assert _inactive_top_after_rise(1.0e4) < 0.35


def _rim_rays(direction, n: int, rng):
    """Points of a floor (z = 0, y > 20) beside a 2 mm block (y < 20) that a sensor along
    ``direction`` (from point to sensor) sees: the block's top, its +y face where the sensor is
    on that side, and the floor outside the block's shadow."""
    x = rng.uniform(5, 35, 3 * n)
    kind = rng.integers(0, 3, 3 * n)  # 0 the top, 1 the floor, 2 the +y face
    y = np.where(kind == 0, rng.uniform(12, 20, 3 * n), rng.uniform(20, 30, 3 * n))
    y = np.where(kind == 2, 20.0, y)
    z = np.where(kind == 2, rng.uniform(0.0, 2.0, 3 * n), np.where(kind == 0, 2.0, 0.0))
    if direction[1] < 0:  # looking along +y: the face is hidden, the floor shadowed
        seen = (kind == 0) | ((kind == 1) & (y >= 20.0 + 2.0 * -direction[1] / direction[2]))
    else:
        seen = np.ones(3 * n, bool)
    pts = np.column_stack([x, y, z])[seen][:n]
    return pts + 95.0 * direction, pts


def test_carved_material_is_inferred_not_a_measured_surface():
    """Active rays hit a 2 mm block's top 0.9 to 1.5 mm from its edge: their band ends inside
    the block, and their walk beyond it leaves the block's side into the free space over the
    floor beside it, then meets the floor, and carves that free space (its run is enclosed
    along the ray). The carved voxels are inferred, not measured: their weight is below the
    monitor's min_weight, so the real-time crossings next to the block are the floor's (or none,
    until the floor is seen again); with the carve's old full weight a false surface stood
    there 1.1 mm above the floor (checked)."""
    facing = DIRECTION * np.array([1.0, -1.0, 1.0])  # a sensor on the floor's side
    for threads in (1, 2):
        rng = np.random.default_rng(11)
        tsdf = SparseTSDF(0.5, 1.5, 8.0, threads=threads)
        for _ in range(3):
            for direction in (DIRECTION, facing):
                o, p = _rim_rays(direction, 100_000, rng)
                tsdf.integrate(o, p, np.zeros(len(p), bool))
        n = 50_000
        p = np.column_stack([rng.uniform(5, 35, n), rng.uniform(18.5, 19.1, n), np.full(n, 2.0)])
        tsdf.integrate(p + 95.0 * DIRECTION, p, np.ones(n, bool))
        origin = np.array([16, 40, -4])  # x 8-32 mm, y 20-21 mm (the two columns beside the
        d, w = tsdf.dense(origin, (48, 2, 12))  # block), z -2 to 4 mm
        carved = (w == CARVE_WEIGHT) & (d == -1.5)
        assert np.count_nonzero(carved) > 20  # the walk did carve there
        cross, _ = column_crossings_weights(d, w, np.float32(1.0))
        z_mm = (origin[2] + cross + 0.5) * 0.5
        seen = np.isfinite(z_mm)  # a column whose floor voxels were carved is unobserved
        assert np.count_nonzero(seen) > 20 and np.max(np.abs(z_mm[seen])) < 0.15, (threads,
                                                                                   z_mm)
