"""Segment flagged vertices into defect regions over mesh connectivity (paper sec. 6.2).

Vertices of the same defect class joined by a mesh edge form one region (connected components,
``scipy.sparse.csgraph``). Regions smaller than ``min_region_area_mm2`` or holding less than
``min_region_volume_mm3`` of deviation are dropped. Each region
carries its surface area, an axis-aligned bounding box in ``O`` enclosing the deviated surface
together with the reference surface beneath it (so its z extent is the defect's height, as the
paper's annotated boxes), its extreme and mean deviation and its centroid.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import sparse
from scipy.sparse.csgraph import connected_components

from dm2.defects.classify import CLASS_NAMES, DEFECT_CLASSES
from dm2.defects.deviation import LayerDeviation


@dataclass(frozen=True)
class Region:
    """One connected defect region of one layer.

    Attributes
    ----------
    layer : int
    kind : str, one of overbuild, underbuild, local_overbuild, local_underbuild
    area_mm2 : float [mm^2], surface area of the region's vertices (barycentric)
    bbox_min_O, bbox_max_O : (3,) float64 [mm], box around region and reference beneath it
    height_mm : float [mm], z extent of that box
    max_deviation_mm : float [mm], the signed deviation of largest magnitude
    mean_deviation_mm : float [mm], area-weighted mean signed deviation
    centroid_O : (3,) float64 [mm], area-weighted centroid of the region's vertices
    vertex_ids : (k,) int64, indices into the layer's vertices
    """

    layer: int
    kind: str
    area_mm2: float
    bbox_min_O: np.ndarray
    bbox_max_O: np.ndarray
    height_mm: float
    max_deviation_mm: float
    mean_deviation_mm: float
    centroid_O: np.ndarray
    vertex_ids: np.ndarray

    def overlaps_xy(self, bbox_min, bbox_max, margin_mm: float = 0.0) -> bool:
        """Whether this region's xy box intersects ``[bbox_min, bbox_max]`` (+ margin)."""
        return bool(np.all(self.bbox_min_O[:2] <= np.asarray(bbox_max)[:2] + margin_mm)
                    and np.all(np.asarray(bbox_min)[:2] - margin_mm <= self.bbox_max_O[:2]))

    def to_dict(self) -> dict:
        return {"layer": self.layer, "kind": self.kind, "area_mm2": self.area_mm2,
                "height_mm": self.height_mm, "max_deviation_mm": self.max_deviation_mm,
                "mean_deviation_mm": self.mean_deviation_mm,
                "centroid_O_mm": self.centroid_O.tolist(),
                "bbox_min_O_mm": self.bbox_min_O.tolist(),
                "bbox_max_O_mm": self.bbox_max_O.tolist(), "n_vertices": int(len(self.vertex_ids))}


def segment_regions(dev: LayerDeviation, min_region_area_mm2: float,
                    min_region_volume_mm3: float = 0.0) -> list[Region]:
    """Connected defect regions of ``dev``, largest first, each at least the minimum area and
    the minimum volume (area-weighted sum of ``|deviation|``)."""
    n = dev.n_vertices
    code = dev.class_code
    flagged = np.isin(code, DEFECT_CLASSES)
    if n == 0 or not flagged.any() or len(dev.faces) == 0:
        return []
    f = dev.faces
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    keep = flagged[e[:, 0]] & (code[e[:, 0]] == code[e[:, 1]])
    e = e[keep]
    graph = sparse.coo_matrix((np.ones(len(e), np.int8), (e[:, 0], e[:, 1])), shape=(n, n))
    _, labels = connected_components(graph, directed=False)
    areas = dev.vertex_areas()
    ids = np.flatnonzero(flagged)
    lab = labels[ids]
    region_area = np.bincount(lab, areas[ids])
    region_volume = np.bincount(lab, areas[ids] * np.abs(dev.signed_distance_mm[ids]))
    big = np.flatnonzero((region_area >= min_region_area_mm2)
                         & (region_volume >= min_region_volume_mm3))
    if big.size == 0:
        return []
    order = np.argsort(lab, kind="stable")
    ids, lab = ids[order], lab[order]
    starts = np.searchsorted(lab, big)
    ends = np.searchsorted(lab, big, side="right")
    regions = [_describe(dev, ids[s:e], areas) for s, e in zip(starts, ends, strict=True)]
    regions.sort(key=lambda r: -r.area_mm2)
    return regions


def _describe(dev: LayerDeviation, vid: np.ndarray, areas: np.ndarray) -> Region:
    pts = dev.vertices_O[vid]
    feet = dev.foot_O[vid]
    both = np.vstack([pts, feet])
    lo, hi = both.min(axis=0), both.max(axis=0)
    a = areas[vid]
    total = float(a.sum())
    wts = a / total if total > 0 else np.full(len(vid), 1.0 / len(vid))
    d = dev.signed_distance_mm[vid]
    return Region(
        layer=int(dev.layer), kind=CLASS_NAMES[int(dev.class_code[vid[0]])], area_mm2=total,
        bbox_min_O=lo, bbox_max_O=hi, height_mm=float(hi[2] - lo[2]),
        max_deviation_mm=float(d[np.argmax(np.abs(d))]), mean_deviation_mm=float(wts @ d),
        centroid_O=wts @ pts, vertex_ids=vid)
