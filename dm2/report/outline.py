"""The part's planned outline in ``O`` (xy polylines) for the report's maps.

From the toolpath when there is one: the sprayed moves of the layer, widened by half a line
spacing, merged, their outer boundary and the boundaries of the holes they leave (a hole wide
enough to hold a disk of ``OUTLINE_HALF_WIDTH_MM``: narrower gaps are slots between lines, not
holes in the part). Without a toolpath: the contour of the near-net reference at half its peak
height.
"""

from __future__ import annotations

import numpy as np

OUTLINE_HALF_WIDTH_MM = 1.0  # half the deposited track width assumed around each sprayed move


def planned_outline(toolpath, layer: int | None = None) -> list[np.ndarray]:
    """Boundaries ``[(k, 2) float64 mm, ...]`` of the sprayed moves of ``layer`` (the last
    layer of the toolpath at or below it; default the last layer): each outer boundary, then
    the holes inside it."""
    from shapely.geometry import LineString, Point, Polygon
    from shapely.ops import unary_union

    layers = np.asarray(toolpath.layer)
    if layers.size == 0:
        return []
    have = np.unique(layers)
    if layer is not None and (have <= layer).any():
        layer = int(have[have <= layer].max())
    else:
        layer = int(have.max())
    pos = np.asarray(toolpath.position_O)[:, :2]
    on = np.asarray(toolpath.spray_on, bool) & (layers == layer)
    shapes = []
    i = 0
    n = len(pos)
    while i < n:  # runs of sprayed moves: the move into point i sprays when spray_on[i]
        if not on[i]:
            i += 1
            continue
        j = i
        while j + 1 < n and on[j + 1]:
            j += 1
        pts = pos[max(i - 1, 0):j + 1]
        shapes.append(LineString(pts) if len(pts) > 1 else Point(pts[0]))
        i = j + 1
    if not shapes:
        return []
    merged = unary_union([s.buffer(OUTLINE_HALF_WIDTH_MM) for s in shapes])
    polys = getattr(merged, "geoms", [merged])
    out = []
    for p in polys:
        if p.area > 1.0:
            out.append(np.asarray(p.exterior.coords))
            out += [np.asarray(h.coords) for h in p.interiors
                    if not Polygon(h).buffer(-OUTLINE_HALF_WIDTH_MM).is_empty]
    return out


def reference_outline(reference) -> list[np.ndarray]:
    """Contours ``[(k, 2) mm, ...]`` of a dm2.reference.height_map.ReferenceMap at half its peak
    height (the near-net part without the overspray)."""
    from skimage.measure import find_contours

    h = np.asarray(reference.heights_mm)
    top = float(h.max()) if h.size else 0.0
    if top <= 0:
        return []
    c = reference.cell_mm
    out = []
    for rc in find_contours(h, 0.5 * top):
        if len(rc) >= 8:
            out.append(np.column_stack([(rc[:, 1] + 0.5) * c, (rc[:, 0] + 0.5) * c]))
    return out
