"""Vectorised polyline geometry for toolpaths: corner rounding, densifying, outward normals.

All functions take and return ``(n, 2)`` float64 arrays of xy points [mm] in O.
"""

from __future__ import annotations

import numpy as np

from dm2.core.tolerances import DIVISOR_FLOOR, ROUNDING_SLACK, SAME_POINT_MM, TURN_EPS_RAD

ARC_STEP_RAD = np.pi / 8  # arcs are drawn with at most 22.5 degrees per segment


def drop_repeats(xy: np.ndarray, tol_mm: float = SAME_POINT_MM) -> np.ndarray:
    """Remove consecutive points closer than ``tol_mm``."""
    xy = np.asarray(xy, dtype=np.float64)
    if len(xy) < 2:
        return xy
    keep = np.ones(len(xy), dtype=bool)
    keep[1:] = np.linalg.norm(np.diff(xy, axis=0), axis=1) > tol_mm
    return xy[keep]


def turning_angles(xy: np.ndarray) -> np.ndarray:
    """Signed turning angle [rad] at each interior vertex, (n-2,); left turns positive."""
    d = np.diff(xy, axis=0)
    a, b = d[:-1], d[1:]
    cross = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    dot = np.einsum("ij,ij->i", a, b)
    return np.arctan2(cross, dot)


def fillet(xy: np.ndarray, radius_mm: float, arc_step_rad: float = ARC_STEP_RAD,
           ) -> tuple[np.ndarray, np.ndarray]:
    """Round every interior corner of an open polyline with a tangent arc.

    As with a robot's zone, the corner path leaves the polyline ``radius_mm`` before the
    corner and rejoins it ``radius_mm`` after it (a 90 degree corner gets an arc of exactly
    that radius; sharper corners a tighter arc, gentler ones a wider arc). The distance is
    limited to half of each adjacent segment so that neighbouring arcs never overlap. End
    points are kept.

    Parameters
    ----------
    xy : (n, 2) float64 [mm]
    radius_mm : float [mm], the zone radius; 0 keeps sharp corners

    Returns
    -------
    out : (m, 2) float64 [mm], the rounded polyline
    source : (m,) int64, index of the input vertex each output point came from
    """
    xy = drop_repeats(xy)
    n = len(xy)
    if n < 3 or radius_mm <= 0:
        return xy, np.arange(n)
    d = np.diff(xy, axis=0)
    seg_len = np.linalg.norm(d, axis=1)
    u = d / seg_len[:, None]
    theta = np.zeros(n)
    theta[1:-1] = turning_angles(xy)
    turn = np.abs(theta) > TURN_EPS_RAD
    half = np.zeros(n)
    half[1:-1] = np.minimum(seg_len[:-1], seg_len[1:]) / 2
    tan_half = np.tan(np.minimum(np.abs(theta), np.pi - TURN_EPS_RAD) / 2)
    t = np.where(turn, np.minimum(radius_mm, half), 0.0)
    r_eff = np.where(turn, t / np.where(turn, tan_half, 1.0), 0.0)
    u_in = np.zeros((n, 2))
    u_in[1:] = u
    normal_left = np.column_stack([-u_in[:, 1], u_in[:, 0]])
    t1 = xy - u_in * t[:, None]
    centre = t1 + normal_left * (r_eff * np.sign(theta))[:, None]
    n_arc = np.where(turn, np.ceil(np.abs(theta) / arc_step_rad), 0).astype(np.int64)
    counts = n_arc + 1
    src = np.repeat(np.arange(n), counts)
    offsets = np.concatenate([[0], np.cumsum(counts)[:-1]])
    j = np.arange(counts.sum()) - offsets[src]
    phi = theta[src] * j / np.maximum(n_arc[src], 1)
    v = t1[src] - centre[src]
    c, s = np.cos(phi), np.sin(phi)
    out = centre[src] + np.column_stack([c * v[:, 0] - s * v[:, 1], s * v[:, 0] + c * v[:, 1]])
    keep = np.ones(len(out), dtype=bool)
    keep[1:] = np.linalg.norm(np.diff(out, axis=0), axis=1) > SAME_POINT_MM  # arcs meet end to end
    return out[keep], src[keep]


def densify(xy: np.ndarray, max_step_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Insert points so no segment is longer than ``max_step_mm``; original points are kept.

    Returns
    -------
    out : (m, 2) float64 [mm]
    source : (m,) int64, index of the input segment end each output point leads to
        (0 for the first point)
    """
    xy = np.asarray(xy, dtype=np.float64)
    if len(xy) < 2:
        return xy, np.zeros(len(xy), dtype=np.int64)
    seg_len = np.linalg.norm(np.diff(xy, axis=0), axis=1)
    n_sub = np.maximum(1, np.ceil(seg_len / max_step_mm - ROUNDING_SLACK)).astype(np.int64)
    seg = np.repeat(np.arange(len(seg_len)), n_sub)
    offsets = np.concatenate([[0], np.cumsum(n_sub)[:-1]])
    frac = (np.arange(n_sub.sum()) - offsets[seg] + 1) / n_sub[seg]
    pts = xy[seg] + (xy[seg + 1] - xy[seg]) * frac[:, None]
    out = np.vstack([xy[:1], pts])
    return out, np.concatenate([[0], seg + 1])


def right_normals_closed(xy: np.ndarray) -> np.ndarray:
    """Unit right-hand normals at the vertices of a closed loop (first point == last point).

    For a ring with the material on its left (exterior counter-clockwise, hole clockwise) the
    right-hand normal points out of the material. Vertex normals average the two adjacent
    segment normals.

    Returns
    -------
    (n, 2) float64, unit vectors
    """
    d = np.diff(xy, axis=0)
    seg_n = np.column_stack([d[:, 1], -d[:, 0]])
    seg_n /= np.maximum(np.linalg.norm(seg_n, axis=1), DIVISOR_FLOOR)[:, None]
    prev = np.vstack([seg_n[-1:], seg_n])  # segment into vertex i (wraps for the start)
    nxt = np.vstack([seg_n, seg_n[:1]])  # segment out of vertex i (wraps for the end)
    v = prev + nxt
    norm = np.linalg.norm(v, axis=1)
    v = np.where(norm[:, None] > SAME_POINT_MM, v / np.maximum(norm, DIVISOR_FLOOR)[:, None], nxt)
    return v
