"""Neighbouring profile points fused as one ray: the merge rule, the weight it carries, and the
surface of a replay with it against the analytic truth."""

from __future__ import annotations

import numpy as np
import pytest
from test_monitor_scene import Scene, make_calibration, raster_lines, raster_run

from dm2.core.config import MonitorConfig, ProcessConfig
from dm2.fusion.fusion import TsdfFusion
from dm2.fusion.profile_merge import merge_profile_points
from dm2.fusion.surface import SurfaceExtractor
from dm2.fusion.tsdf.field import SparseTSDF


def test_runs_within_the_span_merge_and_a_step_or_gap_ends_them():
    # profile 0: four points 0.08 mm apart at z 50, a step of 1 mm, two more; a gap of 1 mm
    # profile 1: one point
    xz = np.array([[0.00, 50.0], [0.08, 50.02], [0.16, 49.98], [0.24, 50.0],  # one run
                   [0.32, 51.0], [0.40, 51.04],  # the step ends the run, a new one
                   [1.40, 51.0],  # a gap along the line ends it
                   [5.0, 40.0]])
    offsets = np.array([0, 7, 8])
    out, off, count = merge_profile_points(xz, offsets, 0.25)
    assert off.tolist() == [0, 3, 4]
    assert count.tolist() == [4, 2, 1, 1]
    np.testing.assert_allclose(out[0], xz[:4].mean(axis=0))
    np.testing.assert_allclose(out[1], xz[4:6].mean(axis=0))
    np.testing.assert_array_equal(out[2:], xz[6:])
    assert count.sum() == len(xz)  # every point is in exactly one ray
    # a span of 0 keeps every point as its own ray
    same, off0, ones = merge_profile_points(xz, offsets, 0.0)
    np.testing.assert_array_equal(same, xz)
    assert off0.tolist() == offsets.tolist() and ones.tolist() == [1] * len(xz)


@pytest.mark.parametrize("active_radius_mm", [0.1, 50.0])
def test_a_ray_of_count_n_weighs_as_n_points_on_it_at_the_caps_too(active_radius_mm):
    """One ray that stands for n points leaves the field that n coincident points leave (the
    same weights, the same distances to rounding), below the weight caps and at them: a
    vertical ray sees the surface at z 9.6 mm twice (weight 2, the cap), then 3 points at z
    9.9 mm. At the cap each point moves a voxel's distance a third of the way (``1 / (cap +
    1)``), so the 3 points leave ``(2/3)**3`` of the old distance's share; one update weighted 3
    would have left ``2/5``. With the active radius of 50 mm the points are active (the stored
    weight capped at 2 before each update), with 0.1 mm they are not (capped after it)."""
    T = np.eye(4)
    T[:3, 3] = (10.1, 10.1, 60.0)
    T[:3, 2] = (0.0, 0.0, -1.0)  # looking down
    T[:3, 0] = (1.0, 0.0, 0.0)
    T[:3, 1] = (0.0, -1.0, 0.0)
    spot, axis = np.array([[10.1, 10.1, 0.0]]), np.array([[0.0, 0.0, -1.0]])
    old = np.array([[0.0, 50.4], [0.0, 50.4]])
    xz = np.array([[0.0, 50.1], [0.0, 50.1], [0.0, 50.1]])
    fields = []
    for pts, count in ((xz, None), (xz[:1], np.array([3]))):
        tsdf = SparseTSDF(0.5, 1.5, weight_cap=2.0, inactive_weight_cap=2.0)
        tsdf.integrate_profiles(old, np.array([0, 2]), T[None], spot, axis, active_radius_mm)
        fused, out = tsdf.integrate_profiles(pts, np.array([0, len(pts)]), T[None], spot, axis,
                                             active_radius_mm, count=count)
        assert (fused, out) == (3, 0)  # measured points, however many rays
        fields.append(tsdf)
    a, b = fields
    assert a.n_blocks == b.n_blocks == 1
    np.testing.assert_array_equal(a.voxels[0, :, 1], b.voxels[0, :, 1])
    np.testing.assert_allclose(a.voxels[0, :, 0], b.voxels[0, :, 0], atol=1e-6)
    # the voxels in front of both surfaces (centres at z 10.25, 10.75, 11.25 mm)
    z_c = np.array([10.25, 10.75, 11.25])
    d, w = a.sample(np.column_stack([np.full(3, 10.25), np.full(3, 10.25), z_c]))
    old_d, new_d = np.clip(z_c - 9.6, -1.5, 1.5), np.clip(z_c - 9.9, -1.5, 1.5)
    np.testing.assert_array_equal(w, 2.0)
    np.testing.assert_allclose(d, new_d + (2.0 / 3.0) ** 3 * (old_d - new_d), atol=1e-5)


def _error(mon, scene):
    v = SurfaceExtractor(mon.tsdf, mon.cfg.min_weight).update().vertices_O
    d = np.abs(scene.sdf(v))
    return float(np.sqrt(np.mean(d ** 2))), float(np.percentile(d, 95)), len(v)


@pytest.mark.slow
def test_merged_rays_fuse_the_same_surface_as_the_points():
    """A box with a sphere cap scanned with 0.05 mm range noise: with neighbouring points fused
    as one ray the surface is as close to the analytic truth (the noise averages within a run),
    every measured point is counted, and the rays are a quarter as many."""
    cal = make_calibration()
    scene = Scene(boxes=[((40, 40, -1), (80, 80, 10))], spheres=[((60, 60, 10), 8.0)])
    msgs, _ = raster_run(scene, cal, raster_lines((35, 85), np.arange(35, 86, 4.0), 10.0),
                         step_mm=1.0, noise_mm=0.05, seed=3)
    runs = {}
    for merge in (0.0, 0.5):
        cfg = MonitorConfig(ray_merge_voxels=merge)
        mon = TsdfFusion(cal, cfg, ProcessConfig(), batch_profiles=96, max_delay_s=np.inf)
        mon.feed_all(msgs)
        mon.finish()
        runs[merge] = (mon, _error(mon, scene))
    (plain, (rms0, p95_0, n0)), (merged, (rms1, p95_1, n1)) = runs[0.0], runs[0.5]
    assert merged.points_fused == plain.points_fused > 100_000
    assert rms1 <= rms0 + 0.005 and p95_1 <= p95_0 + 0.01
    assert rms1 < 0.1 and abs(n1 - n0) < 0.05 * n0
