"""Deviation, classification, segmentation and tracking on synthetic layered pads."""

from types import SimpleNamespace

import numpy as np
import pytest

from dm2.core.config import MonitorConfig
from dm2.defects.classify import LOCAL_OVERBUILD, OVERBUILD, UNDERBUILD, UNOBSERVED
from dm2.defects.deviation import layer_deviation, signed_deviation
from dm2.defects.segment import segment_regions
from dm2.defects.track import RegionTracker
from dm2.reference.height_map import ReferenceMap

CELL = 0.25
LAYER_MM = 0.8
MON = MonitorConfig()  # delta_G 0.4 mm, delta_L 0.5, min_weight 1, min area 4 mm^2


def pad_heights(layer, side_mm=60.0, size=120.0, cell=CELL):
    """Flat-topped square pad centred on the plate, ``layer + 1`` layers tall."""
    n = int(size / cell)
    c = (np.arange(n) + 0.5) * cell
    xx, yy = np.meshgrid(c, c)
    inside = (np.abs(xx - size / 2) <= side_mm / 2) & (np.abs(yy - size / 2) <= side_mm / 2)
    return np.where(inside, LAYER_MM * (layer + 1), 0.0), xx, yy


def gaussian(xx, yy, centre, height, fwhm):
    s = fwhm / 2.3548
    return height * np.exp(-((xx - centre[0]) ** 2 + (yy - centre[1]) ** 2) / (2 * s * s))


def top_surface(heights, lo=(33.0, 33.0), hi=(87.0, 87.0), cell=0.5, weight=1.0):
    """Measured-surface stand-in: the pad top triangulated on a grid of ``cell`` mm."""
    fine = ReferenceMap(heights, CELL)
    n = int(round((hi[0] - lo[0]) / cell)) + 1
    x = np.linspace(lo[0], hi[0], n)
    y = np.linspace(lo[1], hi[1], n)
    xx, yy = np.meshgrid(x, y)
    z = fine.height_at(np.column_stack([xx.ravel(), yy.ravel()]))
    verts = np.column_stack([xx.ravel(), yy.ravel(), z])
    idx = np.arange(n * n).reshape(n, n)
    a, b = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()
    c, d = idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    faces = np.concatenate([np.column_stack([a, b, d]), np.column_stack([a, d, c])])
    w = np.full(len(verts), weight, float)
    return SimpleNamespace(vertices_O=verts, faces=faces, weight=w, normals_O=None)


def bump_truth_area(height, fwhm, delta, cell=0.01):
    """Surface area [mm^2] of the Gaussian bump where it stands more than ``delta`` high."""
    c = np.arange(-10, 10, cell) + cell / 2
    xx, yy = np.meshgrid(c, c)
    h = gaussian(xx, yy, (0, 0), height, fwhm)
    gy, gx = np.gradient(h, cell)
    return float(np.sum(np.sqrt(1 + gx ** 2 + gy ** 2)[h > delta]) * cell * cell)


def test_signed_deviation_sign_and_size_on_open_mesh():
    ref_h, xx, yy = pad_heights(2)
    ref = ReferenceMap(ref_h, CELL, layer=2)
    surf = top_surface(ref_h + 0.6)
    d = signed_deviation(surf, ref)
    assert np.allclose(d, 0.6, atol=1e-4)
    d = signed_deviation(top_surface(ref_h - 0.7), ref)
    assert np.allclose(d, -0.7, atol=1e-4)


def test_bump_found_with_size_and_one_track_id():
    fwhm, height, centre = 5.0, 1.0, (50.0, 70.0)
    tracker = RegionTracker()
    ids_by_layer = {}
    for layer in range(0, 8):
        ref_h, xx, yy = pad_heights(layer)
        meas = ref_h.copy()
        if 3 <= layer <= 6:
            meas += gaussian(xx, yy, centre, height, fwhm)
        dev = layer_deviation(top_surface(meas), ReferenceMap(ref_h, CELL, layer), MON)
        regions = segment_regions(dev, MON.min_region_area_mm2)
        ids_by_layer[layer] = tracker.update(layer, regions)
        if 3 <= layer <= 6:
            assert len(regions) == 1
            r = regions[0]
            assert r.kind == "overbuild"
            truth = bump_truth_area(height, fwhm, MON.delta_global_mm)
            assert abs(r.area_mm2 - truth) <= 0.2 * truth, (r.area_mm2, truth)
            assert abs(r.height_mm - height) <= 0.2
            assert abs(r.max_deviation_mm - height) <= 0.1
            assert np.allclose(r.centroid_O[:2], centre, atol=0.3)
        else:
            assert regions == []
    tracker.finish()
    assert [ids_by_layer[k] for k in (3, 4, 5, 6)] == [[1]] * 4
    assert len(tracker.tracks) == 1
    t = tracker.tracks[0]
    assert (t.kind, t.first_layer, t.last_layer, t.ended_layer) == ("overbuild", 3, 6, 7)
    assert [h["state"] for h in t.history] == ["new", "stable", "stable", "stable"]
    assert t.trend == "stable"


def test_fault_free_surface_gives_no_track():
    rng = np.random.default_rng(3)
    tracker = RegionTracker()
    for layer in range(5):
        ref_h, _, _ = pad_heights(layer)
        meas = ref_h + rng.normal(0.0, 0.03, ref_h.shape)
        dev = layer_deviation(top_surface(meas), ReferenceMap(ref_h, CELL, layer), MON)
        tracker.update(layer, segment_regions(dev, MON.min_region_area_mm2))
    assert tracker.tracks == []


def test_unobserved_region_is_not_underbuild():
    ref_h, xx, yy = pad_heights(4)
    meas = ref_h.copy()
    hole = (np.abs(xx - 60) < 8) & (np.abs(yy - 60) < 8)
    meas[hole] = 0.0  # fused surface falls to the plate where nothing was seen
    surf = top_surface(meas)
    v = surf.vertices_O
    surf.weight[(np.abs(v[:, 0] - 60) < 9) & (np.abs(v[:, 1] - 60) < 9)] = 0.0
    dev = layer_deviation(surf, ReferenceMap(ref_h, CELL, 4), MON)
    in_hole = (np.abs(v[:, 0] - 60) < 8) & (np.abs(v[:, 1] - 60) < 8)
    assert np.all(dev.class_code[in_hole] == UNOBSERVED)
    assert not np.any(dev.class_code == UNDERBUILD)
    assert segment_regions(dev, MON.min_region_area_mm2) == []
    # the same hole, observed, is an underbuild of the right size
    dev = layer_deviation(top_surface(meas), ReferenceMap(ref_h, CELL, 4), MON)
    (r,) = segment_regions(dev, MON.min_region_area_mm2)
    assert r.kind == "underbuild" and r.max_deviation_mm == pytest.approx(-4.0, abs=0.05)
    assert r.height_mm == pytest.approx(4.0, abs=0.05)


def test_global_efficiency_overbuild_area_follows_cross_section():
    tracker = RegionTracker()
    areas = {}
    for layer in range(6):
        side = 54.0 - 6.0 * layer  # the part narrows as it grows
        ref_h, _, _ = pad_heights(layer, side_mm=side + 6.0)
        meas = ref_h * 1.25  # 25 % more material per layer than the reference
        half = side / 2
        surf = top_surface(meas, lo=(60 - half, 60 - half), hi=(60 + half, 60 + half))
        dev = layer_deviation(surf, ReferenceMap(ref_h, CELL, layer), MON)
        regions = segment_regions(dev, MON.min_region_area_mm2)
        tracker.update(layer, regions)
        expected_dev = 0.25 * LAYER_MM * (layer + 1)
        if expected_dev > MON.delta_global_mm:
            (r,) = regions
            assert r.kind == "overbuild"
            assert r.area_mm2 == pytest.approx(side * side, rel=0.02)
            assert r.height_mm == pytest.approx(expected_dev, abs=0.01)
            areas[layer] = r.area_mm2
        else:
            assert regions == []
    assert sorted(areas) == [2, 3, 4, 5]
    assert np.all(np.diff([areas[k] for k in sorted(areas)]) < 0)
    (t,) = tracker.tracks
    assert [h["state"] for h in t.history] == ["new", "shrinking", "shrinking", "shrinking"]
    assert all(h["height_rate_mm_per_layer"] == pytest.approx(0.2, abs=0.01)
               for h in t.history[1:])


def test_local_overbuild_inside_tolerance():
    ref_h, xx, yy = pad_heights(3)
    meas = ref_h + gaussian(xx, yy, (45.0, 45.0), 0.35, 4.0)
    dev = layer_deviation(top_surface(meas), ReferenceMap(ref_h, CELL, 3), MON)
    assert not np.any(dev.class_code == OVERBUILD)
    regions = segment_regions(dev, 1.0)
    assert [r.kind for r in regions] == ["local_overbuild"]
    assert np.allclose(regions[0].centroid_O[:2], (45.0, 45.0), atol=0.3)
    assert np.count_nonzero(dev.class_code == LOCAL_OVERBUILD) == len(regions[0].vertex_ids)
    # a flat offset of the same size is not a local defect
    dev = layer_deviation(top_surface(ref_h + 0.35), ReferenceMap(ref_h, CELL, 3), MON)
    assert segment_regions(dev, 1.0) == []


def test_mean_curvature_of_a_sphere_and_open_boundary():
    import trimesh

    from dm2.defects.classify import boundary_vertices, mean_curvature

    s = trimesh.creation.icosphere(4, radius=5.0)
    h = mean_curvature(s.vertices, s.faces, smooth_iterations=0)
    assert np.median(h) == pytest.approx(0.2, rel=0.03) and h.min() > 0.19
    assert not boundary_vertices(s.vertices, s.faces).any()
    cap = s.submesh([s.vertices[s.faces].mean(axis=1)[:, 2] > 0], append=True)
    border = boundary_vertices(cap.vertices, cap.faces)
    assert border.sum() > 0 and np.abs(cap.vertices[border, 2]).max() < 0.25
    assert np.all(mean_curvature(cap.vertices, cap.faces, smooth_iterations=0)[border] == 0)


def test_reference_resampled_on_voxel_columns():
    n = int(120 / CELL)
    x = (np.arange(n) + 0.5) * CELL
    ramp = np.tile(0.1 * x + 2.0, (n, 1))  # h = 2 + 0.1 x
    ref = ReferenceMap(ramp, CELL, layer=5, stamp_s=3.0)
    vox = ref.resampled(0.5)
    assert vox.heights_mm.shape == (240, 240) and (vox.layer, vox.stamp_s) == (5, 3.0)
    xc = (np.arange(240) + 0.5) * 0.5
    assert np.allclose(vox.heights_mm[7, 10:230], 2.0 + 0.1 * xc[10:230])
    assert np.allclose(vox.height_at([[33.3, 50.0]]), ref.height_at([[33.3, 50.0]]))
