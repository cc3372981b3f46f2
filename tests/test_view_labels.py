"""The 3D view names regions by what they are and keeps the tracks' labels readable."""

from __future__ import annotations

import viser

from dm2.view.scene import Scene, region_label
from tests.chromium import free_port


def test_a_region_is_named_by_its_track_or_as_untracked():
    assert region_label(3, "overbuild") == "#3 overbuild"
    assert region_label(None, "local_overbuild") == "untracked local overbuild"


def test_tracks_are_labelled_and_untracked_regions_only_when_clicked():
    server = viser.ViserServer(host="127.0.0.1", port=free_port(), verbose=False)
    try:
        scene = Scene(server)
        boxes = [(1, "overbuild", (50.0, 50.0, 0.0), (60.0, 60.0, 4.0))] + [
            (None, "local_overbuild", (50.0 + k, 62.0, 3.0), (51.0 + k, 63.0, 4.2))
            for k in range(12)]
        scene.tracks(boxes)
        labels = {h.name: h for h in scene._boxes if h.name.endswith("_label")}
        assert len(labels) == 13
        assert labels["/tracks/1_label"].text == "#1 overbuild"
        assert labels["/tracks/1_label"].visible
        untracked = [labels[f"/regions/{k}_label"] for k in range(1, 13)]
        assert all(h.text == "untracked local overbuild" and not h.visible for h in untracked)
        # a click on a region's box shows its label, a second click hides it again
        box = next(h for h in scene._boxes if h.name == "/regions/5")
        for callback in box._impl.click_cb:
            callback.callback(None)
        assert labels["/regions/5_label"].visible
        assert sum(h.visible for h in untracked) == 1
        for callback in box._impl.click_cb:
            callback.callback(None)
        assert not labels["/regions/5_label"].visible
    finally:
        server.stop()
