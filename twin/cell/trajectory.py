"""Path timing as a robot controller plans it: zones, look-ahead, trapezoidal speed.

The spray target moves along the toolpath polyline through every vertex (the toolpath's own
corners are already rounded). The controller's model:

- **Segment speed.** The move into vertex i runs at most at its programmed ``speed_mm_s[i]``
  and at most at ``max_reorient * L_i / dangle_i`` so the spray axis turns no faster than the
  reorientation limit (axis SLERP along the segment).
- **Corner speed.** A vertex with turn angle ``theta`` (0 = straight on, pi = reversal) and
  zone radius ``z`` is blended by an arc tangent to both segments at distance
  ``d = min(z, L_in / 2, L_out / 2)`` from the vertex, of radius ``R = d / tan(theta / 2)``.
  The speed through the vertex is limited by the path acceleration acting centripetally:
  ``v_corner = sqrt(accel * R)``, and it is held over the length of the blend arc,
  ``R * theta``, centred on the vertex (the target itself stays on the polyline, so it passes
  every vertex exactly). Zone 0 (a fine point), a reversal, the path ends, a requested dwell
  and a pure reorientation all stop the motion (``v = 0``).
- **Look-ahead.** A backward then a forward pass caps every vertex speed so that it can be
  reached from, and braked to, its neighbours with ``|a| <= accel``.
- **Segments** are trapezoids (or triangles) between their end speeds: accelerate at
  ``accel``, cruise, decelerate at ``accel``. A pure reorientation (zero length) turns the
  axis with a smoothstep in time, peak rate ``max_reorient``.

At a raster reversal (two corners joined by the line spacing) the extra residence time over a
straight pass of the same length follows directly: each corner costs the time of braking from
``v`` to ``v_corner`` and back plus the slower crossing of the step.

**Path resolution.** A point closer than ``PATH_RESOLUTION_MM`` (0.01 mm, well under the arm's
0.06 mm repeatability; in :mod:`twin.cell.trajectory_kernels`) to the previous kept one is no move
for the controller: it joins that vertex (its dwell too), and the spray-axis turn it asked for
is made along the next move, under the same reorientation limit. Only an exact repeat with a
new axis stays a pure reorientation. A move that short has no direction of its own; planned as
a corner, its zone (half its length) made a blend of micrometres radius and braked the arm
almost to a stop, and with an axis turn it became a crawl at ``max_reorient * L / angle``.
Sliced contours carry such near-duplicates (every third point of the twisted tower's edge
contours lies 0.2 um from the previous one), and they alone made its edge contours take 2.0
times their programmed time, stuttering between 4 and 27 mm/s along straight sides.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dm2.core.tolerances import (
    SAME_ANGLE_RAD,
    SAME_POINT_MM,
    STRAIGHT_TURN_RAD,
    TINY_DIVISOR_FLOOR,
    TURN_EPS_RAD,
)
from twin.cell.trajectory_kernels import (
    distinct_vertices,
    look_ahead,
    phases,
)


def corner_speed_limit(turn_rad: np.ndarray, zone_mm: np.ndarray, len_in_mm: np.ndarray,
                       len_out_mm: np.ndarray, accel_mm_s2: float) -> np.ndarray:
    """Speed limit [mm/s] through vertices of the given turn angles (see module notes)."""
    turn = np.asarray(turn_rad, dtype=np.float64)
    d = np.minimum(np.asarray(zone_mm, float), np.minimum(len_in_mm, len_out_mm) / 2.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        R = d / np.tan(turn / 2.0)
    v = np.sqrt(accel_mm_s2 * np.clip(R, 0.0, None))
    v = np.where(turn < STRAIGHT_TURN_RAD, np.inf, v)
    v = np.where((d <= 0.0) & (turn >= STRAIGHT_TURN_RAD), 0.0, v)
    return np.where(turn > np.pi - STRAIGHT_TURN_RAD, 0.0, v)


@dataclass(frozen=True)
class PathTiming:
    """A planned path over the compressed vertices of a toolpath.

    Attributes
    ----------
    vertex_index : (k,) int, toolpath index of each kept vertex (coincident repeats dropped)
    group_last : (k,) int, last toolpath index merged into each kept vertex
    position_O : (k, 3) [mm], axis_O : (k, 3) unit, kept vertices
    seg_len_mm : (k,) [mm], length of the move into each kept vertex (0 for the first)
    seg_angle_rad : (k,) [rad], spray-axis turn over that move
    arc_mm : (k,) [mm], path length at each vertex
    v_vertex : (k,) [mm/s], planned speed through each vertex
    arrive_s : (k,) [s], time each vertex is reached; depart_s = arrive_s + dwell
    depart_s : (k,) [s]
    phase_t0 : (p,) [s], phase start times (sorted); phase_seg : (p,) kept index of the move
        (or dwell vertex); phase_s0 : (p,) [mm] arc length at start; phase_v0 : (p,) [mm/s];
        phase_acc : (p,) [mm/s^2]; phase_kind : (p,) 0 move, 1 dwell, 2 reorientation;
        phase_T : (p,) [s] duration
    duration_s : float [s], end of the motion
    """

    vertex_index: np.ndarray
    group_last: np.ndarray
    position_O: np.ndarray
    axis_O: np.ndarray
    seg_len_mm: np.ndarray
    seg_angle_rad: np.ndarray
    arc_mm: np.ndarray
    v_vertex: np.ndarray
    arrive_s: np.ndarray
    depart_s: np.ndarray
    phase_t0: np.ndarray
    phase_seg: np.ndarray
    phase_s0: np.ndarray
    phase_v0: np.ndarray
    phase_acc: np.ndarray
    phase_kind: np.ndarray
    phase_T: np.ndarray
    duration_s: float


def _angles(a0: np.ndarray, a1: np.ndarray) -> np.ndarray:
    c = np.clip(np.einsum("ij,ij->i", a0, a1), -1.0, 1.0)
    s = np.linalg.norm(np.cross(a0, a1), axis=1)
    return np.arctan2(s, c)


def plan_path(position_O: np.ndarray, axis_O: np.ndarray, speed_mm_s: np.ndarray,
              zone_mm: np.ndarray, accel_mm_s2: float, max_reorient_rad_s: float,
              dwell_s: np.ndarray | None = None) -> PathTiming:
    """Plan the timing of a toolpath (see the module notes for the model).

    Parameters
    ----------
    position_O : (n, 3) [mm]; axis_O : (n, 3) unit; speed_mm_s : (n,) [mm/s] programmed speed
        of the move into each point; zone_mm : (n,) [mm]; dwell_s : (n,) [s] extra stop at
        each point (None: no dwell)
    accel_mm_s2 : float [mm/s^2]; max_reorient_rad_s : float [rad/s]
    """
    pos = np.asarray(position_O, dtype=np.float64)
    ax = np.asarray(axis_O, dtype=np.float64)
    n = pos.shape[0]
    if n == 0:
        raise ValueError("plan_path: empty toolpath")
    dwell = np.zeros(n) if dwell_s is None else np.asarray(dwell_s, dtype=np.float64)
    if dwell.shape != (n,) or np.any(dwell < 0) or not np.all(np.isfinite(dwell)):
        raise ValueError(f"dwell: expected ({n},) finite seconds >= 0, got shape {dwell.shape}")
    a = float(accel_mm_s2)
    # Drop repeats within the path resolution (same point and axis to the controller); their
    # dwell joins the kept vertex.
    keep = distinct_vertices(pos, ax)
    idx = np.flatnonzero(keep)
    group = np.cumsum(keep) - 1
    k = idx.size
    dwell_k = np.bincount(group, weights=dwell, minlength=k)
    group_last = np.r_[idx[1:] - 1, n - 1]
    P, A = pos[idx], ax[idx]
    L = np.r_[0.0, np.linalg.norm(np.diff(P, axis=0), axis=1)]
    ang = np.r_[0.0, _angles(A[:-1], A[1:])]
    moving = L > SAME_POINT_MM
    with np.errstate(divide="ignore"):
        v_reor = np.where(ang > SAME_ANGLE_RAD, max_reorient_rad_s * L
                          / np.maximum(ang, TINY_DIVISOR_FLOOR),
                          np.inf)
    v_seg = np.minimum(np.asarray(speed_mm_s, float)[idx], v_reor)
    v_seg[0] = 0.0
    # Corner limits and zones (arc of half-width d around each limited vertex).
    vcorner = np.full(k, np.inf)
    dzone = np.zeros(k)
    if k > 2:
        u = np.diff(P, axis=0) / np.maximum(L[1:, None], TINY_DIVISOR_FLOOR)
        turn = _angles(u[:-1], u[1:])
        zone = np.asarray(zone_mm, float)[idx][1:-1]
        vcorner[1:-1] = corner_speed_limit(turn, zone, L[1:-1], L[2:], a)
        # the blend arc (radius R, turn theta) is R * theta long: cross that at v_corner,
        # centred on the vertex (never longer than the 2 d of polyline it replaces)
        d = np.minimum(zone, np.minimum(L[1:-1], L[2:]) / 2.0)
        with np.errstate(divide="ignore", invalid="ignore"):
            half_arc = 0.5 * turn * d / np.tan(turn / 2.0)
        ok = np.isfinite(vcorner[1:-1]) & (vcorner[1:-1] > 0.0)
        dzone[1:-1] = np.where(ok, np.minimum(half_arc, d), 0.0)
        stop = ~moving[1:-1] | ~moving[2:]
        vcorner[1:-1][stop] = 0.0
        dzone[1:-1][stop] = 0.0
    vcorner[dwell_k > 0] = 0.0
    vcorner[0] = vcorner[-1] = 0.0
    dzone[dwell_k > 0] = 0.0
    arc = np.cumsum(L)
    # Knots: every kept vertex plus the ends of its zone; the zone is crossed at v_corner.
    zi = np.flatnonzero(dzone > SAME_POINT_MM)
    ks = np.r_[arc, arc[zi] - dzone[zi], arc[zi] + dzone[zi]]
    kv = np.r_[vcorner, vcorner[zi], vcorner[zi]]
    kvert = np.r_[np.arange(k), np.full(2 * zi.size, -1)]
    order = np.lexsort((np.r_[np.arange(k), zi - 0.5, zi + 0.5], ks))
    ks, kv, kvert = ks[order], kv[order], kvert[order]
    # Merge a zone knot into a coincident neighbour (zones of adjacent corners may touch).
    drop = np.zeros(ks.size, dtype=bool)
    for j in np.flatnonzero((np.diff(ks) < SAME_POINT_MM) & ((kvert[1:] < 0) | (kvert[:-1] < 0))):
        keep_j, drop_j = (j, j + 1) if kvert[j + 1] < 0 else (j + 1, j)
        kv[keep_j] = min(kv[keep_j], kv[drop_j])
        drop[drop_j] = True
    ks, kv, kvert = ks[~drop], kv[~drop], kvert[~drop]
    # Sub-segment into each knot: owning kept segment and cruise cap.
    mid = np.r_[0.0, 0.5 * (ks[1:] + ks[:-1])]
    owner = np.clip(np.searchsorted(arc, mid, side="left"), 0, k - 1)
    owner = np.where(kvert >= 0, np.maximum(kvert, 0), owner)
    cap = v_seg[owner].copy()
    for near in (owner - 1, owner):
        nj = np.clip(near, 0, k - 1)
        inside = (np.abs(mid - arc[nj]) < dzone[nj]) & (near >= 0)
        cap = np.where(inside, np.minimum(cap, vcorner[nj]), cap)
    kv = np.minimum(kv, np.r_[cap[1:], 0.0])
    kv = np.minimum(kv, cap)
    kv[0] = kv[-1] = 0.0
    kl = np.r_[0.0, np.diff(ks)]
    kv = look_ahead(kv, kl, a)
    ph, arrive, depart, t = phases(ks, kv, kvert, kl, cap, owner, moving, ang, dwell_k, a,
                                    float(max_reorient_rad_s))
    arr = ph
    return PathTiming(
        vertex_index=idx, group_last=group_last, position_O=P, axis_O=A, seg_len_mm=L,
        seg_angle_rad=ang, arc_mm=arc, v_vertex=kv[kvert >= 0], arrive_s=arrive, depart_s=depart,
        phase_t0=arr[:, 0], phase_seg=arr[:, 1].astype(np.int64), phase_s0=arr[:, 2],
        phase_v0=arr[:, 3], phase_acc=arr[:, 4], phase_kind=arr[:, 5].astype(np.int8),
        phase_T=arr[:, 6], duration_s=float(t))


def sample_path(timing: PathTiming, t_s: np.ndarray):
    """Evaluate the planned path at times ``t_s`` (m,) [s].

    Returns
    -------
    position_O : (m, 3) [mm]; axis_O : (m, 3) unit (SLERP along each segment);
    speed_mm_s : (m,) [mm/s]; arc_mm : (m,) [mm]; seg : (m,) kept vertex index of the move
    (or of the vertex dwelt at); dwelling : (m,) bool
    """
    tp = timing
    t = np.clip(np.asarray(t_s, dtype=np.float64), 0.0, tp.duration_s)
    p = np.clip(np.searchsorted(tp.phase_t0, t, side="right") - 1, 0, tp.phase_t0.size - 1)
    tau = np.clip(t - tp.phase_t0[p], 0.0, tp.phase_T[p])
    kind = tp.phase_kind[p]
    seg = tp.phase_seg[p]
    v = np.where(kind == 0, tp.phase_v0[p] + tp.phase_acc[p] * tau, 0.0)
    v = np.maximum(v, 0.0)
    s = tp.phase_s0[p] + np.where(kind == 0, tp.phase_v0[p] * tau + 0.5 * tp.phase_acc[p]
                                  * tau * tau, 0.0)
    prev = np.maximum(seg - 1, 0)
    L = tp.seg_len_mm[seg]
    with np.errstate(divide="ignore", invalid="ignore"):
        u_move = np.clip((s - tp.arc_mm[prev]) / L, 0.0, 1.0)
    x = np.where(tp.phase_T[p] > 0, tau / np.where(tp.phase_T[p] > 0, tp.phase_T[p], 1.0), 1.0)
    u = np.where(kind == 0, u_move, np.where(kind == 2, x * x * (3.0 - 2.0 * x), 1.0))
    u = np.where(seg == 0, 1.0, u)
    p0, p1 = tp.position_O[prev], tp.position_O[seg]
    pos = p0 + u[:, None] * (p1 - p0)
    axis = _slerp_unit(tp.axis_O[prev], tp.axis_O[seg], u)
    return pos, axis, v, s, seg, kind == 1


def _slerp_unit(a0: np.ndarray, a1: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Spherical interpolation between unit vectors (m, 3) at fractions u (m,)."""
    om = _angles(a0, a1)
    if np.any(om > np.pi - TURN_EPS_RAD):
        raise ValueError("spray axis reverses between consecutive toolpath points")
    small = om < SAME_ANGLE_RAD
    so = np.where(small, 1.0, np.sin(om))
    w0 = np.where(small, 1.0 - u, np.sin((1.0 - u) * om) / so)
    w1 = np.where(small, u, np.sin(u * om) / so)
    out = w0[:, None] * a0 + w1[:, None] * a1
    return out / np.linalg.norm(out, axis=1, keepdims=True)
