"""Tracking lifecycle: new, growing, shrinking, merged, split, ended; kind must match."""

import numpy as np

from dm2.defects.segment import Region
from dm2.defects.track import RegionTracker


def region(layer, x0, x1, kind="overbuild", area=None, height=0.5, y=(10.0, 14.0)):
    lo = np.array([x0, y[0], 0.0])
    hi = np.array([x1, y[1], height])
    area = (x1 - x0) * (y[1] - y[0]) if area is None else area
    return Region(layer, kind, float(area), lo, hi, height, height, height / 2,
                  (lo + hi) / 2, np.arange(3))


def states(track):
    return [(h["layer"], h["state"]) for h in track.history]


def test_merge_split_and_end():
    tr = RegionTracker(margin_mm=0.5)
    assert tr.update(0, [region(0, 0, 4), region(0, 10, 14)]) == [1, 2]
    assert tr.update(1, [region(1, 0, 6), region(1, 10, 13)]) == [1, 2]  # grow / shrink
    # both grow into one region: it continues the older track, the other ends merged
    assert tr.update(2, [region(2, 0, 14)]) == [1]
    t1, t2 = tr.tracks
    assert t2.ended and t2.ended_layer == 2 and t2.merged_into == 1
    # the merged region splits in two: the larger keeps the id, the other is new with parent 1
    assert tr.update(3, [region(3, 0, 4), region(3, 8, 14)]) == [3, 1]
    t3 = tr.tracks[2]
    assert t3.parent == 1 and t3.first_layer == 3
    # a region of another kind in the same place is not the same defect
    assert tr.update(4, [region(4, 8, 14), region(4, 0, 4, kind="underbuild")]) == [1, 4]
    assert t3.ended and t3.ended_layer == 4 and not t1.ended
    tr.finish()
    assert states(t1) == [(0, "new"), (1, "growing"), (2, "merged"), (3, "split"), (4, "stable")]
    assert states(t2) == [(0, "new"), (1, "shrinking")]
    assert states(t3) == [(3, "new")]
    assert tr.tracks[3].kind == "underbuild"
    assert all(t.ended for t in tr.tracks) and tr.active == []


def test_a_track_holding_two_regions_is_matched_against_both_next_layer():
    """A region merged into a track that continues elsewhere belongs to it: the next layer's
    region in its place continues that track instead of opening a new one."""
    tr = RegionTracker(margin_mm=0.5)
    assert tr.update(0, [region(0, 0, 20), region(0, 30, 34)]) == [1, 2]
    # the second region reaches the first track's box: it merges into track 1, which also
    # continues in the first region (the larger one, recorded in its history)
    assert tr.update(1, [region(1, 0, 20), region(1, 19.8, 34, area=10.0)]) == [1, 1]
    t1, t2 = tr.tracks
    assert t2.ended and t2.merged_into == 1
    assert t1.bbox_min_O[0] == 0.0 and t1.bbox_max_O[0] == 34.0  # both regions' boxes
    # only the merged region's place stays flagged: still track 1, no new track
    assert tr.update(2, [region(2, 30, 34)]) == [1]
    assert len(tr.tracks) == 2 and not t1.ended
    assert states(t1) == [(0, "new"), (1, "split"), (2, "shrinking")]


def test_growth_rates_and_trend():
    tr = RegionTracker()
    for layer, (x1, h) in enumerate([(4, 0.5), (5, 0.7), (6, 0.9), (7, 1.1)]):
        tr.update(layer, [region(layer, 0, x1, height=h)])
    (t,) = tr.tracks
    assert t.trend == "amplifying"
    assert [round(h["area_rate_mm2_per_layer"], 6) for h in t.history] == [0, 4, 4, 4]
    assert np.allclose([h["height_rate_mm_per_layer"] for h in t.history[1:]], 0.2)
    tr2 = RegionTracker()
    for layer, h in enumerate([1.2, 0.9, 0.6]):
        tr2.update(layer, [region(layer, 0, 4, height=h)])
    assert tr2.tracks[0].trend == "self-compensating"
    assert [s for _, s in states(tr2.tracks[0])] == ["new", "shrinking", "shrinking"]
