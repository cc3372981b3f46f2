"""Overhang detection: where a layer's outline extends beyond the layer below."""

from __future__ import annotations

import numpy as np
import shapely

from dm2.core.messages import KIND_CODE
from dm2.core.tolerances import GEOMETRY_SLACK_MM


def overhang_regions(regions, min_mm: float) -> list:
    """Per layer, the part of its region farther than ``min_mm`` outside the layer below.

    Parameters
    ----------
    regions : sequence of shapely (Multi)Polygons in O [mm], one per layer
    min_mm : float [mm], growth beyond the layer below that counts as overhang

    Returns
    -------
    list of prepared shapely geometries (empty for layer 0 and where nothing overhangs)
    """
    out = [shapely.Polygon()]
    for below, here in zip(regions[:-1], regions[1:], strict=True):
        if here.is_empty:
            out.append(shapely.Polygon())
            continue
        grown = here.buffer(GEOMETRY_SLACK_MM)
        ov = grown.difference(below.buffer(min_mm)) if not below.is_empty else grown
        if not ov.is_empty:
            shapely.prepare(ov)
        out.append(ov)
    return out


def classify_overhang(xy: np.ndarray, kind: np.ndarray, overhang, probe_offset_xy=None
                      ) -> np.ndarray:
    """Turn spraying moves whose midpoint lies in ``overhang`` into kind overhang.

    Parameters
    ----------
    xy : (n, 2) float64 [mm], the stroke's points (point 0 is where the stroke starts)
    kind : (n - 1,) int8, kind of the move into points 1..n-1
    overhang : shapely geometry (possibly empty)
    probe_offset_xy : optional (n - 1, 2) [mm], shift of each midpoint before testing (edge
        strokes probe the outline they build, half a bead outward)

    Returns
    -------
    (n - 1,) int8 kinds
    """
    if overhang.is_empty or len(xy) < 2:
        return kind
    mid = (xy[1:] + xy[:-1]) / 2
    if probe_offset_xy is not None:
        mid = mid + probe_offset_xy
    hit = shapely.contains_xy(overhang, mid[:, 0], mid[:, 1])
    return np.where(hit, np.int8(KIND_CODE["overhang"]), kind).astype(np.int8)
