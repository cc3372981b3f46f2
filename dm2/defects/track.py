"""Track defect regions across layers (paper sec. 6.2: bounding-box intersection).

A region continues a track when its xy bounding box intersects the track's last box (plus a
margin) and its kind matches. Per layer a track is in one state:

* ``new``; ``growing`` (amplifying), ``shrinking`` (self-compensating) or ``stable``, judged
  on the area change (beyond ``area_tolerance``) and otherwise on the height change (beyond
  ``height_tolerance_mm``);
* ``merged``: several tracks met one region; it continues the oldest, the others end;
* ``split``: one track met several regions; the largest continues it, the rest start new tracks
  (their ``parent`` is the split track);
* ``ended``: no region continued it this layer.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from dm2.defects.segment import Region

TREND_NAMES = ("amplifying", "self-compensating", "stable")


@dataclass(eq=False)
class Track:
    """One defect followed across layers.

    ``history`` holds, per layer seen, a dict with layer, state, area_mm2, height_mm,
    max_deviation_mm, centroid_O_mm and the growth rates (per layer) of area, height and max
    deviation since the previous observation.
    """

    id: int
    kind: str
    first_layer: int
    last_layer: int
    history: list[dict] = field(default_factory=list)
    ended: bool = False
    ended_layer: int | None = None
    parent: int | None = None
    merged_into: int | None = None
    bbox_min_O: np.ndarray = field(default_factory=lambda: np.zeros(3))
    bbox_max_O: np.ndarray = field(default_factory=lambda: np.zeros(3))

    @property
    def trend(self) -> str:
        """``amplifying`` / ``self-compensating`` / ``stable`` from the fitted height slope."""
        if len(self.history) < 2:
            return "stable"
        layers = np.array([h["layer"] for h in self.history], float)
        height = np.array([h["height_mm"] for h in self.history])
        area = np.array([h["area_mm2"] for h in self.history])
        h_slope = np.polyfit(layers, height, 1)[0]
        a_slope = np.polyfit(layers, area, 1)[0] / max(area.mean(), 1e-9)
        if h_slope > 0.02 or (abs(h_slope) <= 0.02 and a_slope > 0.05):
            return "amplifying"
        if h_slope < -0.02 or (abs(h_slope) <= 0.02 and a_slope < -0.05):
            return "self-compensating"
        return "stable"

    def series(self, key: str) -> tuple[np.ndarray, np.ndarray]:
        """``(layers, values)`` of one history field, e.g. ``area_mm2``."""
        return (np.array([h["layer"] for h in self.history], int),
                np.array([h[key] for h in self.history], float))

    def to_dict(self) -> dict:
        return {"id": self.id, "kind": self.kind, "first_layer": self.first_layer,
                "last_layer": self.last_layer, "ended": self.ended,
                "ended_layer": self.ended_layer, "parent": self.parent,
                "merged_into": self.merged_into, "trend": self.trend,
                "area_mm2": {str(h["layer"]): h["area_mm2"] for h in self.history},
                "height_mm": {str(h["layer"]): h["height_mm"] for h in self.history},
                "history": self.history}


class RegionTracker:
    """Associate each layer's regions with persistent track ids.

    Parameters
    ----------
    margin_mm : float [mm], xy slack added to the boxes before testing intersection
    area_tolerance : float, relative area change below which a track is not growing/shrinking
    height_tolerance_mm : float [mm], height change below which it is stable
    """

    def __init__(self, margin_mm: float = 1.0, area_tolerance: float = 0.1,
                 height_tolerance_mm: float = 0.05):
        self.margin_mm = float(margin_mm)
        self.area_tolerance = float(area_tolerance)
        self.height_tolerance_mm = float(height_tolerance_mm)
        self.tracks: list[Track] = []
        self._active: list[Track] = []

    @property
    def active(self) -> list[Track]:
        return list(self._active)

    def update(self, layer: int, regions: list[Region]) -> list[int]:
        """Assign ``regions`` of ``layer`` to tracks; returns the track id of each region."""
        act = self._active
        hit = np.zeros((len(act), len(regions)), bool)
        for i, t in enumerate(act):
            for j, r in enumerate(regions):
                hit[i, j] = r.kind == t.kind and r.overlaps_xy(t.bbox_min_O, t.bbox_max_O,
                                                               self.margin_mm)
        owner: list[Track | None] = [None] * len(regions)
        state = [""] * len(regions)
        for j in range(len(regions)):
            cands = [act[i] for i in np.flatnonzero(hit[:, j])]
            if len(cands) > 1:
                keep = min(cands, key=lambda t: t.id)
                owner[j], state[j] = keep, "merged"
                for t in cands:
                    if t is not keep:
                        t.merged_into = keep.id
                        hit[act.index(t), :] = False
                hit[act.index(keep), j] = True
        for i, t in enumerate(act):
            mine = [j for j in np.flatnonzero(hit[i]) if owner[j] is None or owner[j] is t]
            if not mine:
                continue
            best = max(mine, key=lambda j: regions[j].area_mm2)
            for j in mine:
                if j == best:
                    owner[j] = t
                    state[j] = state[j] or ("split" if len(mine) > 1 else "")
                elif owner[j] is None:
                    state[j] = "new:split"
                    owner[j] = self._new_track(layer, regions[j], parent=t.id)
        ids = []
        still = []
        for j, r in enumerate(regions):
            t = owner[j]
            if t is None:
                t = owner[j] = self._new_track(layer, r)
                st = "new"
            elif state[j] == "new:split":
                st = "new"
            else:
                st = state[j] or self._change_state(t, r)
            self._record(t, r, st)
            ids.append(t.id)
            if t not in still:
                still.append(t)
        for t in act:
            if t not in still:
                t.ended, t.ended_layer = True, layer
        self._active = still
        return ids

    def finish(self, layer: int | None = None) -> None:
        """End every active track (end of the build); ``layer`` is recorded as where it ended."""
        for t in self._active:
            t.ended = True
            t.ended_layer = t.last_layer + 1 if layer is None else layer
        self._active = []

    def _new_track(self, layer: int, r: Region, parent: int | None = None) -> Track:
        t = Track(id=len(self.tracks) + 1, kind=r.kind, first_layer=layer, last_layer=layer,
                  parent=parent)
        self.tracks.append(t)
        return t

    def _change_state(self, t: Track, r: Region) -> str:
        prev = t.history[-1]
        rel = (r.area_mm2 - prev["area_mm2"]) / max(prev["area_mm2"], 1e-9)
        if rel > self.area_tolerance:
            return "growing"
        if rel < -self.area_tolerance:
            return "shrinking"
        dh = r.height_mm - prev["height_mm"]
        if dh > self.height_tolerance_mm:
            return "growing"
        if dh < -self.height_tolerance_mm:
            return "shrinking"
        return "stable"

    def _record(self, t: Track, r: Region, state: str) -> None:
        if t.history and t.history[-1]["layer"] == r.layer:  # a merge already recorded it
            return
        if t.history:
            prev = t.history[-1]
            gap = max(r.layer - prev["layer"], 1)
            rates = {"area_rate_mm2_per_layer": (r.area_mm2 - prev["area_mm2"]) / gap,
                     "height_rate_mm_per_layer": (r.height_mm - prev["height_mm"]) / gap,
                     "max_deviation_rate_mm_per_layer":
                         (r.max_deviation_mm - prev["max_deviation_mm"]) / gap}
        else:
            rates = {"area_rate_mm2_per_layer": 0.0, "height_rate_mm_per_layer": 0.0,
                     "max_deviation_rate_mm_per_layer": 0.0}
        t.history.append({"layer": r.layer, "state": state, "area_mm2": r.area_mm2,
                          "height_mm": r.height_mm, "max_deviation_mm": r.max_deviation_mm,
                          "mean_deviation_mm": r.mean_deviation_mm,
                          "centroid_O_mm": r.centroid_O.tolist(), **rates})
        t.last_layer = r.layer
        t.bbox_min_O, t.bbox_max_O = r.bbox_min_O.copy(), r.bbox_max_O.copy()
