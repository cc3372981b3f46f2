"""Slice a watertight part mesh into per-layer regions (shapely polygons) in the plate plane.

Layer ``k`` is sprayed onto ``z_O = k * layer_mm``; its region is the mesh's cross-section at
the layer's mid-height ``(k + 0.5) * layer_mm``. A part of height ``h`` therefore gives every
layer whose mid-height lies below its top: ``round(h / layer_mm)`` layers.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import shapely
import trimesh
from shapely.geometry import MultiPolygon, Polygon
from trimesh import intersections

from dm2.core.tolerances import ROUNDING_SLACK, SIMPLIFY_MM

log = logging.getLogger(__name__)

MIN_REGION_AREA_MM2 = 1e-3  # cross-section pieces smaller than this are slicing noise


@dataclass(frozen=True)
class SlicedPart:
    """Per-layer regions of a part.

    Attributes
    ----------
    layer_mm : float [mm], layer thickness
    z_mid_mm : (n,) float64 [mm], slicing height of each layer in O
    regions : tuple of n shapely (Multi)Polygons in the O xy-plane [mm]; exteriors oriented
        counter-clockwise and holes clockwise (material on the left of every ring)
    """

    layer_mm: float
    z_mid_mm: np.ndarray
    regions: tuple

    @property
    def n_layers(self) -> int:
        return len(self.regions)

    def layer_z_mm(self) -> np.ndarray:
        """(n,) float64 [mm], the surface each layer is sprayed onto: ``k * layer_mm``."""
        return np.arange(self.n_layers, dtype=np.float64) * self.layer_mm


def count_layers(top_z_mm: float, layer_mm: float) -> int:
    """Number of layers whose mid-height ``(k + 0.5) * layer_mm`` lies below ``top_z_mm``."""
    if layer_mm <= 0:
        raise ValueError(f"toolpath.layer_mm: must be positive, got {layer_mm}")
    return max(0, int(np.floor(top_z_mm / layer_mm + 0.5 - ROUNDING_SLACK)))


def _section_region(segments_2d: np.ndarray) -> Polygon | MultiPolygon:
    if len(segments_2d) == 0:
        return Polygon()
    path = trimesh.load_path(segments_2d)
    polys = [p for p in path.polygons_full if p is not None and p.area > MIN_REGION_AREA_MM2]
    if not polys:
        return Polygon()
    region = shapely.make_valid(shapely.union_all(polys))
    region = shapely.simplify(region, SIMPLIFY_MM)  # drop collinear section vertices
    parts = [g for g in shapely.get_parts(region)
             if isinstance(g, Polygon) and g.area > MIN_REGION_AREA_MM2]
    if not parts:
        return Polygon()
    region = parts[0] if len(parts) == 1 else MultiPolygon(parts)
    return shapely.orient_polygons(region, exterior_cw=False)


def slice_mesh(mesh_O: trimesh.Trimesh, layer_mm: float, max_layers: int | None = None
               ) -> SlicedPart:
    """Slice ``mesh_O`` (in O, base at z = 0) at every layer's mid-height.

    Parameters
    ----------
    mesh_O : watertight trimesh in the work-object frame [mm]
    layer_mm : float [mm], layer thickness (> 0)
    max_layers : optional cap on the number of layers

    Returns
    -------
    SlicedPart
    """
    if mesh_O is None or len(mesh_O.faces) == 0:
        raise ValueError("part mesh is empty")
    n = count_layers(float(mesh_O.bounds[1, 2]), layer_mm)
    if max_layers is not None:
        n = min(n, int(max_layers))
    if n == 0:
        raise ValueError(f"part is lower than half a layer ({layer_mm} mm): nothing to slice")
    z_mid = (np.arange(n) + 0.5) * layer_mm
    lines, to_3d, _ = intersections.mesh_multiplane(mesh_O, np.zeros(3), np.array([0.0, 0, 1]),
                                                    z_mid)
    regions = []
    for seg, T in zip(lines, to_3d, strict=True):
        seg = np.asarray(seg, dtype=np.float64).reshape(-1, 2)
        xy = seg @ T[:2, :2].T + T[:2, 3]
        regions.append(_section_region(xy.reshape(-1, 2, 2)))
    areas = [r.area for r in regions]
    if max(areas) <= 0:
        raise ValueError("part mesh has no cross-section above the plate (is its base at z=0?)")
    log.debug("sliced %d layers of %.3f mm, areas %.1f..%.1f mm^2", n, layer_mm,
              min(areas), max(areas))
    return SlicedPart(float(layer_mm), z_mid, tuple(regions))
