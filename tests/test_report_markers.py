"""The numbered markers of the per-layer deviation maps: tracked regions only."""

from types import SimpleNamespace

import numpy as np

from dm2.report.contents import MAP_MARKERS, layer_markers


def _region(kind, x, y):
    return SimpleNamespace(kind=kind, centroid_O=np.array([x, y, 1.0]))


def test_only_tracked_regions_get_a_number_and_the_tracks_kind():
    result = SimpleNamespace(
        regions=[_region("underbuild", 10.0, 20.0), _region("overbuild", 30.0, 40.0),
                 _region("local_overbuild", 50.0, 60.0)],
        track_ids=[None, 4, 7])
    marks = layer_markers(result, {4: "overbuild", 7: "overbuild"})
    # the untracked underbuild region has no marker; track 7 is named by its track's kind
    assert marks == [(4, "overbuild", (30.0, 40.0)), (7, "overbuild", (50.0, 60.0))]


def test_at_most_map_markers_per_layer():
    n = MAP_MARKERS + 5
    result = SimpleNamespace(regions=[_region("overbuild", float(i), 0.0) for i in range(n)],
                             track_ids=list(range(1, n + 1)))
    marks = layer_markers(result, {})
    assert [m[0] for m in marks] == list(range(1, MAP_MARKERS + 1))
