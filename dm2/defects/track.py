"""Track defect regions across layers (paper sec. 6.2: bounding-box intersection).

A region continues a track when its xy bounding box intersects the track's last box (plus a
margin) and its deviation has the same sign: a defect whose class changes between local and
global (a bump that outgrows ``delta_global_mm``, or an overbuild that shrinks back into the
tolerance) keeps its id, and the class of every layer is kept in its history (``kinds``).
A track's ``kind`` is its global class once it has been global, else its local class.

Evidence over time: a region opens a *candidate*; the candidate becomes a track only once it
has been seen in ``confirm_observations`` layers within ``confirm_window_layers`` layers of its
first (so its onset stays the layer it was first seen in). A candidate that does not make it
is dropped: a single noisy layer never opens a track. With ``confirm_requires_global`` a
candidate seen only as local over/underbuild is not confirmed either (local deviations stay
early warnings in the layer results) until the region turns global within the window; its
``first_layer`` (onset) is then the first global layer, ``warned_from`` the first local one,
and the history keeps both. Track
ids are numbered in the order tracks are confirmed. Per layer a track is in one state:

* ``new``; ``growing`` (amplifying), ``shrinking`` (self-compensating) or ``stable``, judged
  on the area change (beyond ``area_tolerance``) and otherwise on the height change (beyond
  ``height_tolerance_mm``);
* ``merged``: several tracks met one region; it continues the oldest confirmed one (among
  candidates only: one seen global before local-only ones, then the oldest), the others end.
  A track that so holds several regions in a layer (its history records the largest) is
  matched against all their boxes in the next layer: the region it took over stays its own,
  not a new track (on the full twisted tower, one flank region had been reported as four
  tracks in turn);
* ``split``: one track met several regions; the largest continues it, the rest start new tracks
  (their ``parent`` is the split track);
* ``ended``: no region continued it this layer.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from dm2.core.tolerances import RATIO_FLOOR
from dm2.defects.segment import Region

TREND_NAMES = ("amplifying", "self-compensating", "stable")


@dataclass(eq=False)
class Track:
    """One defect followed across layers.

    ``history`` holds, per layer seen, a dict with layer, state, area_mm2, height_mm,
    max_deviation_mm, centroid_O_mm and the growth rates (per layer) of area, height and max
    deviation since the previous observation.
    """

    id: int | None
    kind: str
    first_layer: int
    last_layer: int
    history: list[dict] = field(default_factory=list)
    ended: bool = False
    ended_layer: int | None = None
    parent: int | Track | None = None  # a Track object only while that one is a candidate
    merged_into: int | Track | None = None
    bbox_min_O: np.ndarray = field(default_factory=lambda: np.zeros(3))
    bbox_max_O: np.ndarray = field(default_factory=lambda: np.zeros(3))
    confirmed: bool = False
    serial: int = 0
    warned_from: int | None = None  # first layer of a local early warning before the onset
    observations: list[tuple[int, int]] = field(default_factory=list)  # (layer, region index)

    @property
    def kinds(self) -> dict[int, str]:
        """Class per layer seen, ``{layer: kind}`` (local and global classes may alternate)."""
        return {h["layer"]: h["kind"] for h in self.history}

    @property
    def trend(self) -> str:
        """``amplifying`` / ``self-compensating`` / ``stable`` from the fitted height slope."""
        if len(self.history) < 2:
            return "stable"
        layers = np.array([h["layer"] for h in self.history], float)
        height = np.array([h["height_mm"] for h in self.history])
        area = np.array([h["area_mm2"] for h in self.history])
        h_slope = np.polyfit(layers, height, 1)[0]
        a_slope = np.polyfit(layers, area, 1)[0] / max(area.mean(), RATIO_FLOOR)
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
                "ended_layer": self.ended_layer, "parent": _track_id(self.parent),
                "merged_into": _track_id(self.merged_into), "trend": self.trend,
                "kinds": {str(k): v for k, v in self.kinds.items()},
                "warned_from_layer": self.warned_from,
                "area_mm2": {str(h["layer"]): h["area_mm2"] for h in self.history},
                "height_mm": {str(h["layer"]): h["height_mm"] for h in self.history},
                "history": self.history}


def _track_id(link) -> int | None:
    """A parent / merged-into link as a track id (None while it names an unconfirmed one)."""
    return link.id if isinstance(link, Track) else link


class RegionTracker:
    """Associate each layer's regions with persistent track ids.

    Parameters
    ----------
    margin_mm : float [mm], xy slack added to the boxes before testing intersection
    area_tolerance : float, relative area change below which a track is not growing/shrinking
    height_tolerance_mm : float [mm], height change below which it is stable
    confirm_observations : int, layers a candidate must be seen in to become a track
    confirm_window_layers : int, ... within this many layers from its first
    confirm_requires_global : bool, ... and once at least in a global class
    """

    def __init__(self, margin_mm: float = 1.0, area_tolerance: float = 0.1,
                 height_tolerance_mm: float = 0.05, confirm_observations: int = 1,
                 confirm_window_layers: int = 2, confirm_requires_global: bool = False):
        if confirm_observations < 1 or confirm_window_layers < confirm_observations:
            raise ValueError(f"RegionTracker: need 1 <= confirm_observations "
                             f"({confirm_observations}) <= confirm_window_layers "
                             f"({confirm_window_layers})")
        self.confirm_observations = int(confirm_observations)
        self.confirm_window_layers = int(confirm_window_layers)
        self.confirm_requires_global = bool(confirm_requires_global)
        self.newly_confirmed: list[Track] = []
        self._next_id = 1
        self._serial = 0
        self.margin_mm = float(margin_mm)
        self.area_tolerance = float(area_tolerance)
        self.height_tolerance_mm = float(height_tolerance_mm)
        self._all: list[Track] = []
        self._active: list[Track] = []

    @property
    def tracks(self) -> list[Track]:
        """Confirmed tracks, in the order they were confirmed (= id order)."""
        return sorted((t for t in self._all if t.confirmed), key=lambda t: t.id)

    @property
    def candidates(self) -> list[Track]:
        """Regions seen but not (yet) confirmed as tracks."""
        return [t for t in self._all if not t.confirmed]

    @property
    def active(self) -> list[Track]:
        return [t for t in self._active if t.confirmed]

    @staticmethod
    def _same_sign(a: str, b: str) -> bool:
        return a.endswith("overbuild") == b.endswith("overbuild")

    def update(self, layer: int, regions: list[Region]) -> list[int | None]:
        """Assign ``regions`` of ``layer`` to tracks; returns the track id of each region (None
        for a region only a candidate holds so far). Tracks confirmed by this layer are listed
        in ``newly_confirmed`` with the ``observations`` (layer, region index) they hold."""
        self.newly_confirmed = []
        act = self._active
        hit = np.zeros((len(act), len(regions)), bool)
        for i, t in enumerate(act):
            for j, r in enumerate(regions):
                hit[i, j] = self._same_sign(r.kind, t.kind) and r.overlaps_xy(
                    t.bbox_min_O, t.bbox_max_O, self.margin_mm)
        owner: list[Track | None] = [None] * len(regions)
        state = [""] * len(regions)
        for j in range(len(regions)):
            cands = [act[i] for i in np.flatnonzero(hit[:, j])]
            if len(cands) > 1:
                # a confirmed track continues; among candidates one seen global keeps its
                # evidence (a merge into a local-only candidate would drop it)
                keep = min(cands, key=lambda t: (not t.confirmed, t.kind.startswith("local_"),
                                                 t.first_layer, t.serial))
                owner[j], state[j] = keep, "merged"
                for t in cands:
                    if t is not keep:
                        t.merged_into = keep
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
                    owner[j] = self._new_track(layer, regions[j], parent=t)
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
            t.observations.append((layer, j))
            if t not in still:
                still.append(t)
        for t in still:
            if not t.confirmed and len(t.history) >= self.confirm_observations and (
                    not self.confirm_requires_global or not t.kind.startswith("local_")):
                self._confirm(t)
        for t in act:
            if t not in still:
                t.ended, t.ended_layer = True, layer
        # candidates that can no longer be confirmed in their window are dropped
        last = layer - self.confirm_window_layers + 1
        self._all = [t for t in self._all
                     if t.confirmed or (not t.ended and t.first_layer >= last)]
        self._active = [t for t in still if t.confirmed or t.first_layer >= last]
        self._resolve_links()
        return [t.id for t in owner]

    def _confirm(self, t: Track) -> None:
        if self.confirm_requires_global:  # onset: the first global layer; local ones warned
            glob = [h["layer"] for h in t.history if not h["kind"].startswith("local_")]
            t.warned_from = t.first_layer
            t.first_layer = min(glob)
        t.confirmed = True
        t.id = self._next_id
        self._next_id += 1
        self.newly_confirmed.append(t)

    def _resolve_links(self) -> None:
        """``merged_into`` and ``parent`` name track ids once the tracks named are confirmed."""
        for t in self._all:
            for name in ("merged_into", "parent"):
                other = getattr(t, name)
                if isinstance(other, Track):
                    if other.confirmed:
                        setattr(t, name, other.id)
                    elif other not in self._all:
                        setattr(t, name, None)

    def finish(self, layer: int | None = None) -> None:
        """End every active track (end of the build); ``layer`` is recorded as where it ended."""
        for t in self._active:
            t.ended = True
            t.ended_layer = t.last_layer + 1 if layer is None else layer
        self._active = []
        self._all = [t for t in self._all if t.confirmed]
        self._resolve_links()

    def _new_track(self, layer: int, r: Region, parent: int | None = None) -> Track:
        t = Track(id=None, kind=r.kind, first_layer=layer, last_layer=layer, parent=parent)
        self._serial += 1
        t.serial = self._serial  # creation order (candidates have no id yet)
        self._all.append(t)
        return t

    def _change_state(self, t: Track, r: Region) -> str:
        prev = t.history[-1]
        rel = (r.area_mm2 - prev["area_mm2"]) / max(prev["area_mm2"], RATIO_FLOOR)
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
            # it holds this region too: the next layer is matched against all it holds
            t.bbox_min_O = np.minimum(t.bbox_min_O, r.bbox_min_O)
            t.bbox_max_O = np.maximum(t.bbox_max_O, r.bbox_max_O)
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
        if not r.kind.startswith("local_") or t.kind.startswith("local_"):
            t.kind = r.kind  # global once it has been global
        t.history.append({"layer": r.layer, "state": state, "kind": r.kind,
                          "area_mm2": r.area_mm2,
                          "height_mm": r.height_mm, "max_deviation_mm": r.max_deviation_mm,
                          "mean_deviation_mm": r.mean_deviation_mm,
                          "centroid_O_mm": r.centroid_O.tolist(), **rates})
        t.last_layer = r.layer
        t.bbox_min_O, t.bbox_max_O = r.bbox_min_O.copy(), r.bbox_max_O.copy()
