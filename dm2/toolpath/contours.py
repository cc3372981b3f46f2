"""Edge (contour) loops: a layer's outline inset by half a bead, opened near a start point."""

from __future__ import annotations

import numpy as np
import shapely

from dm2.core.tolerances import SIMPLIFY_MM, SQUARED_LENGTH_FLOOR_MM2

MITRE_LIMIT = 10.0  # keep sharp corners sharp when insetting (a 45 degree corner needs 2.6)


def contour_loops(region, inset_mm: float) -> list[np.ndarray]:
    """The rings of ``region`` inset by ``inset_mm``, material on the left of each.

    Parameters
    ----------
    region : shapely (Multi)Polygon in O [mm], oriented (exterior CCW, holes CW)
    inset_mm : float [mm], >= 0

    Returns
    -------
    list of (k, 2) float64 [mm] closed rings (first point == last point): exteriors
    counter-clockwise, holes clockwise, so the right-hand normal points out of the material
    """
    if region.is_empty:
        return []
    inset = region.buffer(-inset_mm, join_style="mitre", mitre_limit=MITRE_LIMIT) \
        if inset_mm > 0 else region
    if inset.is_empty:
        return []
    inset = shapely.orient_polygons(shapely.simplify(inset, SIMPLIFY_MM), exterior_cw=False)
    loops = []
    for poly in shapely.get_parts(inset):
        if poly.is_empty or poly.geom_type != "Polygon":
            continue
        loops.append(np.asarray(poly.exterior.coords, dtype=np.float64))
        loops.extend(np.asarray(r.coords, dtype=np.float64) for r in poly.interiors)
    return [lp for lp in loops if len(lp) >= 4]


def open_loop_near(loop: np.ndarray, point_xy: np.ndarray, keep_clear_mm: float) -> np.ndarray:
    """Re-start a closed loop at the point of it nearest to ``point_xy``.

    The start is moved to the middle of its edge when it would fall within ``keep_clear_mm`` of
    a corner, so that every corner of the loop is an interior vertex (and can be rounded).

    Returns
    -------
    (k + 2, 2) float64 [mm], closed (first point == last point)
    """
    a, b = loop[:-1], loop[1:]
    ab = b - a
    L2 = np.maximum(np.einsum("ij,ij->i", ab, ab), SQUARED_LENGTH_FLOOR_MM2)
    s = np.clip(np.einsum("ij,ij->i", point_xy - a, ab) / L2, 0.0, 1.0)
    proj = a + ab * s[:, None]
    i = int(np.argmin(np.linalg.norm(proj - point_xy, axis=1)))
    length = np.sqrt(L2[i])
    along = s[i] * length
    if along < keep_clear_mm or length - along < keep_clear_mm:
        along = length / 2
    start = a[i] + ab[i] * (along / length)
    body = np.vstack([loop[i + 1:-1], loop[:i + 1]])
    return np.vstack([start, body, start])


def corner_angles_deg(loop: np.ndarray) -> np.ndarray:
    """Interior (material-side) angle [deg] at each vertex of a closed loop, (k-1,).

    Left turns (convex corners) give angles below 180, right turns (reflex) above.
    """
    ring = loop[:-1]
    d_in = ring - np.roll(ring, 1, axis=0)
    d_out = np.roll(ring, -1, axis=0) - ring
    cross = d_in[:, 0] * d_out[:, 1] - d_in[:, 1] * d_out[:, 0]
    dot = np.einsum("ij,ij->i", d_in, d_out)
    return 180.0 - np.degrees(np.arctan2(cross, dot))
