"""Layer-by-layer defect monitoring: deviation, classification, segmentation and tracking.

Wires the stages of the paper's section 6 for one finished layer: the measured surface (from
dm2.fusion.fusion) against the near-net reference of the same layer (dm2.reference.model) gives a
:class:`~dm2.defects.deviation.LayerDeviation`, whose flagged vertices are segmented into regions
and
associated with persistent tracks.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np

from dm2.defects.classify import CLASS_NAMES
from dm2.defects.deviation import LayerDeviation, layer_deviation
from dm2.defects.segment import Region, segment_regions
from dm2.defects.track import RegionTracker
from dm2.io.spill import SpillStore
from dm2.reference.height_map import ReferenceMap

log = logging.getLogger(__name__)


@dataclass
class LayerResult:
    """Everything the report needs about one layer.

    Attributes
    ----------
    layer : int
    deviation : LayerDeviation
    reference : ReferenceMap
    regions : list of Region, largest first
    track_ids : list of int, the track of each region
    timing_s : dict stage -> wall seconds (deviation, segment, track)
    """

    layer: int
    deviation: LayerDeviation
    reference: ReferenceMap
    regions: list[Region]
    track_ids: list[int]
    timing_s: dict = field(default_factory=dict)

    def statistics(self) -> dict:
        """Per-layer summary: deviation percentiles and area per class [mm^2]; with the seen
        surface, ``stale_top``: the area [mm^2] of the vertices read as an old top grown over
        unseen and the largest gap [mm] they were lifted by."""
        dev = self.deviation
        areas = dev.vertex_areas()
        seen = dev.class_code != CLASS_NAMES.index("unobserved")
        d = dev.signed_distance_mm[seen]
        stats = {"n_vertices": dev.n_vertices, "surface_area_mm2": float(areas.sum()),
                 "area_by_class_mm2": {name: float(areas[dev.class_code == k].sum())
                                       for k, name in enumerate(CLASS_NAMES)}}
        if dev.model_inflation is not None:  # dm2.defects.uncertainty_online
            stats["uncertainty_inflation"] = dict(dev.model_inflation)
        stale = getattr(dev, "stale_mm", None)
        if stale is not None:  # what the stale-top rule lifted (dm2.defects.stale), in sight
            lifted = stale > 0.0
            stats["stale_top"] = {"area_mm2": float(areas[lifted].sum()),
                                  "max_gap_mm": float(stale.max()) if lifted.any() else 0.0}
        if d.size:
            w = areas[seen]
            stats.update({
                "deviation_min_mm": float(d.min()), "deviation_max_mm": float(d.max()),
                "deviation_mean_mm": float(np.average(d, weights=w) if w.sum() > 0 else d.mean()),
                "deviation_rms_mm": float(np.sqrt(np.mean(d * d))),
                "deviation_p05_mm": float(np.percentile(d, 5)),
                "deviation_p95_mm": float(np.percentile(d, 95))})
        return stats


class LayerAnalysis:
    """Analyse finished layers against their references and keep the tracks.

    Parameters
    ----------
    monitor_cfg : MonitorConfig (delta_global_mm, delta_local, min_weight, min_region_area_mm2)
    tracker : RegionTracker or None (default settings)
    same_grid : bool, compare against the reference as the measurement represents it: point
        sampled at the TSDF voxel columns (see ReferenceMap.resampled), as the paper runs
        reference and measurement through the same volumetric representation
    outline : dm2.defects.footprint.PlannedOutline or None, the planned footprint (enables
        the overspray class)
    uncertainty : bool, classify against each vertex's confidence bound
        (dm2.defects.uncertainty); False applies the paper's thresholds alone

    The default tracker confirms a region as a track once it has been seen in
    ``track_min_observations`` layers within ``track_window_layers``, and (unless
    ``track_local_alone``) once in a global class; the layer results of the layers before its
    confirmation get its id then.

    Only the newest ``monitor_cfg.layers_in_memory`` results keep their deviation and reference
    in memory; older ones are read back from a scratch folder when asked for
    (:mod:`dm2.io.spill`).
    """

    def __init__(self, monitor_cfg, tracker: RegionTracker | None = None,
                 same_grid: bool = True, outline=None, uncertainty: bool = True):
        self.cfg = monitor_cfg
        self.same_grid = bool(same_grid)
        self.outline = outline
        self.uncertainty = bool(uncertainty)
        self.tracker = tracker or RegionTracker(
            confirm_observations=monitor_cfg.track_min_observations,
            confirm_window_layers=max(monitor_cfg.track_window_layers,
                                      monitor_cfg.track_min_observations),
            confirm_requires_global=not monitor_cfg.track_local_alone)
        self.results: list[LayerResult] = []
        keep = getattr(monitor_cfg, "layers_in_memory", None)
        self.spill = SpillStore(keep) if keep is not None else None

    def analyse_layer(self, surface, reference: ReferenceMap, layer: int | None = None,
                      stamp_s: float | None = None, unseen: ReferenceMap | None = None,
                      seen_surface=None) -> LayerResult:
        """Deviation, segmentation and tracking of one layer's surface; returns its result.
        ``unseen``: the reference's growth since each column was last observed (or None);
        ``seen_surface``: the height last seen per column (dm2.defects.stale.SeenSurface, or
        None)."""
        layer = reference.layer if layer is None else int(layer)
        t0 = time.perf_counter()
        compared = reference
        if self.same_grid and reference.cell_mm < self.cfg.voxel_mm:
            compared = reference.resampled(self.cfg.voxel_mm)
        dev = layer_deviation(surface, compared, self.cfg, layer, stamp_s, outline=self.outline,
                              uncertainty=self.uncertainty, unseen=unseen,
                              seen_surface=seen_surface)
        t1 = time.perf_counter()
        regions = segment_regions(dev, self.cfg.min_region_area_mm2,
                                  self.cfg.min_region_volume_mm3)
        t2 = time.perf_counter()
        ids = self.tracker.update(layer, regions)
        t3 = time.perf_counter()
        res = LayerResult(layer, dev, reference, regions, ids,
                          {"deviation": t1 - t0, "segment": t2 - t1, "track": t3 - t2})
        self.results.append(res)
        if self.spill is not None:
            self.spill.spill_old(self.results, "deviation")
            self.spill.spill_old(self.results, "reference")
        by_layer = {r.layer: r for r in self.results}
        for track in self.tracker.newly_confirmed:  # earlier layers' regions get the id now
            for seen_layer, j in track.observations:
                if seen_layer in by_layer:
                    by_layer[seen_layer].track_ids[j] = track.id
        log.info("layer %d: %d region(s) %s", layer, len(regions),
                 ", ".join(f"{r.kind} {r.area_mm2:.0f} mm2" for r in regions[:5]))
        return res

    def finish(self) -> None:
        """End all tracks (after the last layer)."""
        self.tracker.finish()
