"""Evidence over time: a region becomes a track only when it persists; a defect keeps its id
when its class changes between local and global."""

import numpy as np

from dm2.defects.segment import Region
from dm2.defects.track import RegionTracker


def region(layer, x0, x1, kind="overbuild", height=0.5):
    lo, hi = np.array([x0, 10.0, 0.0]), np.array([x1, 14.0, height])
    return Region(layer, kind, float((x1 - x0) * 4.0), lo, hi, height, height, height / 2,
                  (lo + hi) / 2, np.arange(3))


def test_single_layer_noise_never_opens_a_track():
    tr = RegionTracker(confirm_observations=2, confirm_window_layers=2)
    for layer in range(6):  # a blip somewhere else in every layer, never twice in one place
        assert tr.update(layer, [region(layer, 10.0 * layer, 10.0 * layer + 3)]) == [None]
    tr.finish()
    assert tr.tracks == [] and tr.candidates == []


def test_persistent_region_is_confirmed_with_its_first_layer():
    tr = RegionTracker(confirm_observations=2, confirm_window_layers=2)
    assert tr.update(3, [region(3, 0, 4), region(3, 30, 33)]) == [None, None]
    assert tr.tracks == []
    assert tr.update(4, [region(4, 0, 5)]) == [1]
    (t,) = tr.tracks
    assert (t.id, t.first_layer, t.last_layer) == (1, 3, 4)
    assert tr.newly_confirmed == [t] and t.observations == [(3, 0), (4, 0)]
    assert [h["layer"] for h in t.history] == [3, 4]
    tr.update(5, [])
    tr.finish()
    assert len(tr.tracks) == 1  # the one-layer region at x = 30 was dropped


def test_class_change_local_to_global_keeps_the_track_id():
    tr = RegionTracker()
    assert tr.update(1, [region(1, 0, 4, kind="local_overbuild", height=0.3)]) == [1]
    assert tr.update(2, [region(2, 0, 5, kind="overbuild", height=0.6)]) == [1]
    assert tr.update(3, [region(3, 0, 5, kind="local_overbuild", height=0.35)]) == [1]
    # the opposite sign in the same place is another defect
    assert tr.update(4, [region(4, 0, 5, kind="local_underbuild")]) == [2]
    t1, t2 = tr.tracks
    assert t1.kind == "overbuild"  # global once it has been global
    assert t1.kinds == {1: "local_overbuild", 2: "overbuild", 3: "local_overbuild"}
    assert t1.to_dict()["kinds"] == {"1": "local_overbuild", "2": "overbuild",
                                     "3": "local_overbuild"}
    assert t1.ended and t1.ended_layer == 4 and t2.kind == "local_underbuild"


def test_local_only_region_is_an_early_warning_until_it_turns_global():
    tr = RegionTracker(confirm_observations=2, confirm_window_layers=2,
                       confirm_requires_global=True)
    assert tr.update(1, [region(1, 0, 4, kind="local_overbuild", height=0.3),
                         region(1, 20, 24, kind="local_underbuild")]) == [None, None]
    assert tr.update(2, [region(2, 0, 4, kind="local_overbuild", height=0.35),
                         region(2, 20, 24, kind="local_underbuild")]) == [None, None]
    assert tr.tracks == []  # two layers of local deviation: early warnings only
    # the bump turns global: its track opens with the local layers as its history
    assert tr.update(3, [region(3, 0, 5, kind="overbuild", height=0.6),
                         region(3, 20, 24, kind="local_underbuild")]) == [1, None]
    (t,) = tr.tracks
    assert t.kind == "overbuild" and t.first_layer == 3 and t.warned_from == 1
    assert t.kinds == {1: "local_overbuild", 2: "local_overbuild", 3: "overbuild"}
    tr.finish()
    assert len(tr.tracks) == 1  # the dent never turned global: no track


def test_a_merge_keeps_the_global_evidence():
    """A region that meets a global candidate and an older local-only one continues the global
    one: merged into the local candidate, whose window ends, the global layer would be lost."""
    tr = RegionTracker(confirm_observations=2, confirm_window_layers=2,
                       confirm_requires_global=True)
    assert tr.update(3, [region(3, 0, 3, kind="local_overbuild", height=0.3)]) == [None]
    # layer 4: the local bump goes on at x 0-3; a global overbuild opens beside it at x 5-9
    assert tr.update(4, [region(4, 5, 9, kind="overbuild", height=0.8),
                         region(4, 0, 3, kind="local_overbuild", height=0.3)]) == [None, None]
    # layer 5: one region over both, back under delta_global_mm
    assert tr.update(5, [region(5, 0, 9, kind="local_overbuild", height=0.35)]) == [1]
    (t,) = tr.tracks
    assert t.kind == "overbuild" and t.first_layer == 4 and t.last_layer == 5
    assert t.kinds == {4: "overbuild", 5: "local_overbuild"}
    tr.finish()
    assert len(tr.tracks) == 1
