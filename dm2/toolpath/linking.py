"""Link strokes into one continuous (C3D-style) path: raster ordering and skip-move routing.

Powder flows all the time, so the path never stops spraying; pieces that cannot be joined by a
short move inside the layer's region are joined by fast *skip* moves, routed along the
contour rings (inside the material) rather than across holes where the straight line would
leave the region.
"""

from __future__ import annotations

import numpy as np
import shapely
from shapely.geometry import LineString, Point

from dm2.core.messages import KIND_CODE
from dm2.core.tolerances import GEOMETRY_SLACK_MM, SAME_POINT_MM
from dm2.toolpath.polyline import drop_repeats

LINK_FACTOR = 2.5  # raster ends closer than this many spacings (inside the region) are joined
CONTAIN_TOL_MM = GEOMETRY_SLACK_MM
DOWN_O = np.array([0.0, 0.0, -1.0])


class Region:
    """A layer region prepared for containment tests plus its travel rings for skip routing.

    Parameters
    ----------
    polygon : shapely (Multi)Polygon in O [mm]
    travel_loops : list of (k, 2) closed rings inside the material (the contour loops)
    """

    def __init__(self, polygon, travel_loops: list[np.ndarray]):
        self.polygon = polygon
        self._tol = polygon.buffer(CONTAIN_TOL_MM)
        shapely.prepare(self._tol)
        self.rings = [shapely.linearrings(lp) for lp in travel_loops]
        self._loops = travel_loops

    def contains_line(self, a: np.ndarray, b: np.ndarray) -> bool:
        return bool(self._tol.contains(LineString([a, b])))

    def route(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """Waypoints (excluding ``a``, ending with ``b``) of a skip from ``a`` to ``b``, (w, 2)."""
        b = np.asarray(b, dtype=np.float64)
        if np.linalg.norm(b - a) < SAME_POINT_MM or self.contains_line(a, b) or not self.rings:
            return b[None]
        outside = LineString([a, b]).difference(self._tol)
        i = int(np.argmin([r.distance(outside) for r in self.rings]))
        return drop_repeats(np.vstack([_walk_ring(self._loops[i], self.rings[i], a, b), b]))


def _walk_ring(loop: np.ndarray, ring, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Points along ``ring`` from the foot of ``a`` to the foot of ``b``, the shorter way."""
    total = ring.length
    sa, sb = ring.project(Point(a)), ring.project(Point(b))
    verts = loop[:-1]
    cum = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(loop, axis=0), axis=1))])[:-1]
    fwd = (sb - sa) % total
    if fwd <= total / 2:
        rel = (cum - sa) % total
        pick = np.flatnonzero((rel > 0) & (rel < fwd))
    else:
        rel = (sa - cum) % total
        pick = np.flatnonzero((rel > 0) & (rel < total - fwd))
    pick = pick[np.argsort(rel[pick])]
    start = np.asarray(ring.interpolate(sa).coords[0])
    end = np.asarray(ring.interpolate(sb).coords[0])
    return np.vstack([start, verts[pick], end])


def order_raster(segments: np.ndarray, scanline: np.ndarray, start_xy: np.ndarray,
                 region: Region, spacing_mm: float) -> list[np.ndarray]:
    """Order raster pieces greedily from ``start_xy`` into boustrophedon chains.

    The first piece is the end of the first or last raster line nearest to ``start_xy`` (so
    the raster sweeps from one side to the other). Each next piece is the one with the
    nearest free end; it joins the current chain when the
    link is at most ``LINK_FACTOR * spacing_mm`` long and stays inside the region, otherwise it
    starts a new chain (to be reached by a skip move).

    Parameters
    ----------
    segments : (m, 2, 2) float64 [mm]
    scanline : (m,) int64, raster line index of each piece
    start_xy : (2,) float64 [mm], where the nozzle is now

    Returns
    -------
    list of (k, 2) float64 polylines (the chains, in spraying order)
    """
    m = len(segments)
    if m == 0:
        return []
    free = np.ones(m, dtype=bool)
    ends = segments.reshape(m * 2, 2)
    cur = np.asarray(start_xy, dtype=np.float64)
    chains: list[list[np.ndarray]] = []
    outer = np.repeat((scanline == scanline.min()) | (scanline == scanline.max()), 2)
    for step in range(m):
        d = np.linalg.norm(ends - cur, axis=1)
        d[np.repeat(~free, 2)] = np.inf
        if step == 0:
            d[~outer] = np.inf
        j = int(np.argmin(d))
        i, flipped = divmod(j, 2)
        seg = segments[i][::-1] if flipped else segments[i]
        free[i] = False
        if chains and d[j] <= LINK_FACTOR * spacing_mm and region.contains_line(cur, seg[0]):
            chains[-1].append(seg)
        else:
            chains.append([seg])
        cur = seg[1]
    return [drop_repeats(np.vstack(c)) for c in chains]


class PathBuilder:
    """Accumulates toolpath rows: positions, axes, kinds, layers (no speeds yet)."""

    def __init__(self):
        self._xy: list[np.ndarray] = []
        self._z: list[np.ndarray] = []
        self._axis: list[np.ndarray] = []
        self._kind: list[np.ndarray] = []
        self._layer: list[np.ndarray] = []
        self.n_points = 0
        self.pos_xy: np.ndarray | None = None

    def _append(self, xy, z, axis, kind, layer):
        k = len(xy)
        if k == 0:
            return
        self._xy.append(np.asarray(xy, dtype=np.float64))
        self._z.append(np.full(k, z, dtype=np.float64))
        self._axis.append(np.broadcast_to(np.asarray(axis, dtype=np.float64), (k, 3)))
        self._kind.append(np.broadcast_to(np.asarray(kind, dtype=np.int8), (k,)))
        self._layer.append(np.full(k, layer, dtype=np.int32))
        self.n_points += k
        self.pos_xy = np.asarray(xy[-1], dtype=np.float64)

    def move_to(self, target_xy: np.ndarray, region: Region, layer: int, z_mm: float,
                axis_at_target: np.ndarray, kind_if_first: int) -> None:
        """Reach ``target_xy`` by a skip move (routed inside ``region``) if not already there.

        Intermediate skip waypoints spray straight down; the arrival point already carries the
        axis of the stroke it leads into, so the robot re-orients during the fast move.
        """
        target_xy = np.asarray(target_xy, dtype=np.float64)
        if self.pos_xy is None:
            self._append(target_xy[None], z_mm, axis_at_target, kind_if_first, layer)
            return
        if np.linalg.norm(target_xy - self.pos_xy) < SAME_POINT_MM:
            return
        route = region.route(self.pos_xy, target_xy)
        route = route[np.cumsum(np.linalg.norm(route - self.pos_xy, axis=1) > SAME_POINT_MM) > 0]
        if len(route) > 1:
            self._append(route[:-1], z_mm, DOWN_O, KIND_CODE["skip"], layer)
        self._append(route[-1:], z_mm, axis_at_target, KIND_CODE["skip"], layer)

    def spray(self, xy: np.ndarray, axis: np.ndarray, kind: np.ndarray, layer: int,
              z_mm: float) -> None:
        """Append spraying points (the moves into them have kinds ``kind``)."""
        self._append(xy, z_mm, axis, kind, layer)

    def arrays(self) -> dict[str, np.ndarray]:
        if not self._xy:
            raise ValueError("toolpath is empty: the part has no sprayable region")
        xy = np.vstack(self._xy)
        return {
            "position_O": np.column_stack([xy, np.concatenate(self._z)]),
            "axis_O": np.vstack(self._axis),
            "kind": np.concatenate(self._kind),
            "layer": np.concatenate(self._layer),
        }
