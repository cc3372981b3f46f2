"""A stale top (dm2.defects.stale): a measured top below what the profilers last saw all around
it is an old top the new one grew over unseen, not an underbuild; a dent the profilers saw at
its own depth stays an underbuild, and so does a wall."""

from __future__ import annotations

import numpy as np
from test_deviation import CELL, MON, pad_heights, top_surface

from dm2.defects.classify import UNDERBUILD
from dm2.defects.deviation import layer_deviation
from dm2.defects.segment import segment_regions
from dm2.defects.stale import STALE_MARGIN_MM, STALE_REACH_MM, TOP_MIN_NZ, SeenSurface, stale_gap_mm
from dm2.reference.height_map import ReferenceMap

PATCH = (55.0, 65.0)  # x and y range [mm] of the old top, 3.2 mm below the new one


def _stale_pad():
    ref_h, xx, yy = pad_heights(9)  # 8.0 mm tall
    meas = ref_h.copy()
    patch = (xx >= PATCH[0]) & (xx <= PATCH[1]) & (yy >= PATCH[0]) & (yy <= PATCH[1])
    meas[patch] -= 3.2
    return ref_h, meas, patch


def _seen(heights_mm):
    return SeenSurface(np.asarray(heights_mm, np.float64), CELL)


def test_a_top_below_what_was_seen_in_its_column_is_lifted_and_nothing_else():
    ref_h, meas, patch = _stale_pad()
    ref = ReferenceMap(ref_h, CELL, layer=9)
    surf = top_surface(meas)
    plain = layer_deviation(surf, ref, MON)
    low = plain.signed_distance_mm < -3.0
    assert low.sum() > 300 and np.all(plain.class_code[low] == UNDERBUILD)  # 100 mm^2 deep
    # the profilers last saw the whole top at 8.0 mm (the points of the neighbouring columns)
    seen = layer_deviation(surf, ref, MON, seen_surface=_seen(ref_h))
    lifted = seen.stale_mm > 0
    assert np.abs(seen.signed_distance_mm[lifted]).max() < 0.05  # lifted to what was seen
    # the rim's vertices within the margin of the top keep their deviation, and no region is
    # left: nothing is reported
    assert np.abs(seen.signed_distance_mm).max() <= STALE_MARGIN_MM
    assert segment_regions(seen, MON.min_region_area_mm2) == []
    assert np.allclose(seen.stale_mm[low], 3.2, atol=0.05)
    sound = np.abs(plain.signed_distance_mm) < 0.01
    assert np.all(seen.stale_mm[sound] == 0.0)
    assert np.array_equal(seen.signed_distance_mm[sound], plain.signed_distance_mm[sound])


def test_a_dent_seen_at_its_own_depth_stays_an_underbuild_of_its_size():
    ref_h, meas, patch = _stale_pad()
    ref = ReferenceMap(ref_h, CELL, layer=9)
    surf = top_surface(meas)
    plain = layer_deviation(surf, ref, MON)
    # its own points saw the dent (the neighbours' rim 0.9 mm higher than the point would be
    # within the margin): the seen surface is the measured one
    seen = layer_deviation(surf, ref, MON, seen_surface=_seen(meas))
    assert np.array_equal(seen.signed_distance_mm, plain.signed_distance_mm)
    assert np.array_equal(seen.class_code, plain.class_code)
    regions = segment_regions(seen, MON.min_region_area_mm2)
    assert len(regions) == 1 and regions[0].kind == "underbuild"
    assert abs(regions[0].max_deviation_mm + 3.2) < 0.05
    assert np.allclose(regions[0].bbox_min_O[:2], PATCH[0], atol=0.5)  # the dent, its walls in
    assert np.allclose(regions[0].bbox_max_O[:2], PATCH[1], atol=0.5)


def test_the_gap_counts_beyond_the_margin_below_everything_seen_within_reach():
    cell = 0.25
    seen = SeenSurface(np.full((40, 40), 5.0), cell)
    seen.heights_mm[0, 0] = -np.inf  # never seen
    seen.heights_mm[20:, 30:] = 0.0  # the plate beyond a wall at x = 7.5, y >= 5 mm
    v = np.array([[3.1, 3.1, 2.0],    # 3 mm below all seen around it: 3 mm
                  [3.1, 3.1, 5.0 - STALE_MARGIN_MM + 0.01],  # within the margin: 0
                  [0.1, 0.1, 2.0],    # a never-seen cell within reach: 0
                  [20.0, 1.0, 2.0],   # off the grid: 0
                  [3.1, 3.1, 6.0],    # above what was seen: 0
                  [7.5 - STALE_REACH_MM + 0.05, 7.0, 2.0],  # a wall: the plate within reach
                  [7.5 - STALE_REACH_MM - 0.3, 7.0, 2.0]])  # farther in: lifted
    assert np.allclose(stale_gap_mm(v, seen), [3.0, 0, 0, 0, 0, 0, 3.0])
    assert stale_gap_mm(v, None) is None


def test_an_up_facing_vertex_is_also_held_to_its_own_cell():
    """Inside an old top, a cell last seen long ago on that old top (expected 1 mm above it)
    holds the window's lowest value down; a vertex that faces up is lifted by its own cell,
    which was seen on the new top. A wall's vertex in the same place is not."""
    cell = 0.25
    seen = SeenSurface(np.full((40, 40), 5.0), cell)
    seen.heights_mm[12, 13] = 3.0  # a neighbour last seen on the old top at 2.0 (+1 mm grown)
    v = np.array([[3.1, 3.1, 2.0], [3.1, 3.1, 2.0]])
    up = np.cos(np.radians(44.0))
    n = np.array([[0.0, np.sqrt(1.0 - up * up), up], [1.0, 0.0, 0.0]])
    assert n[0, 2] >= TOP_MIN_NZ > np.cos(np.radians(46.0))
    assert np.allclose(stale_gap_mm(v, seen), [0.0, 0.0])  # the window's 3.0: within margin
    assert np.allclose(stale_gap_mm(v, seen, None, n), [3.0, 0.0])
    # the unseen growth of its own column counts first: 2.5 mm of it leaves 0.5, not stale
    assert np.allclose(stale_gap_mm(v, seen, np.array([2.5, 2.5]), n), [0.0, 0.0])


def test_the_layer_statistics_keep_what_was_lifted_in_sight():
    """What the rule lifts is never hidden: report.json's layer statistics carry the lifted
    area (the old top and its steep rim: what read as underbuild without the rule) and the
    largest gap; a dent seen at its depth lifts nothing and stays an underbuild."""
    from dm2.defects.layer_analysis import LayerAnalysis

    ref_h, meas, patch = _stale_pad()
    ref = ReferenceMap(ref_h, CELL, layer=9)
    surf = top_surface(meas)
    plain = LayerAnalysis(MON).analyse_layer(surf, ref, 9).statistics()
    under = plain["area_by_class_mm2"]["underbuild"]
    assert under > 150.0 and "stale_top" not in plain
    lifted = LayerAnalysis(MON).analyse_layer(surf, ref, 9, None, None, _seen(ref_h))
    stats = lifted.statistics()
    assert stats["stale_top"]["max_gap_mm"] == 3.2 and lifted.regions == []
    assert abs(stats["stale_top"]["area_mm2"] - under) < 5.0
    assert stats["area_by_class_mm2"]["underbuild"] == 0.0
    dent = LayerAnalysis(MON).analyse_layer(surf, ref, 9, None, None, _seen(meas)).statistics()
    assert dent["stale_top"] == {"area_mm2": 0.0, "max_gap_mm": 0.0}
    assert dent["area_by_class_mm2"]["underbuild"] == under
