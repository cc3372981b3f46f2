"""Compiled loops of the controller's path timing (:mod:`twin.cell.trajectory`): which points the
controller moves to, the look-ahead speed caps and the trapezoid phases in time order."""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from dm2.core.tolerances import SAME_ANGLE_RAD, SAME_POINT_MM

# closer points are one point to the controller (see twin.cell.trajectory)
PATH_RESOLUTION_MM = 0.01


@njit(cache=True)
def distinct_vertices(pos: np.ndarray, ax: np.ndarray) -> np.ndarray:
    """Mask (n,) of the points the controller moves to: farther than the path resolution from
    the last kept point, or exactly on it with another spray axis (a pure reorientation)."""
    n = pos.shape[0]
    keep = np.zeros(n, dtype=np.bool_)
    if n == 0:
        return keep
    keep[0] = True
    last = 0
    for i in range(1, n):
        d = math.sqrt((pos[i, 0] - pos[last, 0]) ** 2 + (pos[i, 1] - pos[last, 1]) ** 2
                      + (pos[i, 2] - pos[last, 2]) ** 2)
        if d > PATH_RESOLUTION_MM:
            keep[i] = True
            last = i
        elif d <= SAME_POINT_MM:
            c = ax[i, 0] * ax[last, 0] + ax[i, 1] * ax[last, 1] + ax[i, 2] * ax[last, 2]
            s = math.sqrt((ax[i, 1] * ax[last, 2] - ax[i, 2] * ax[last, 1]) ** 2
                          + (ax[i, 2] * ax[last, 0] - ax[i, 0] * ax[last, 2]) ** 2
                          + (ax[i, 0] * ax[last, 1] - ax[i, 1] * ax[last, 0]) ** 2)
            if math.atan2(s, c) > SAME_ANGLE_RAD:
                keep[i] = True
                last = i
    return keep


@njit(cache=True)
def phases(ks, kv, kvert, kl, cap, owner, moving, ang, dwell_k, a, max_reorient):
    """Trapezoid phases between knots, reorientations and dwells, in time order.

    Returns (phases (p, 7): t0, seg, s0, v0, acc, kind, T; arrive (k,); depart (k,); end time).
    """
    k = moving.size
    ph = np.zeros((3 * ks.size + 2 * k + 1, 7))
    arrive = np.zeros(k)
    depart = np.zeros(k)
    n = 0
    t = 0.0
    for j in range(ks.size):
        i = kvert[j]
        if j > 0 and kl[j] > SAME_POINT_MM:
            v0, v1, vc, Lj = kv[j - 1], kv[j], cap[j], kl[j]
            vp = max(min(vc, math.sqrt(a * Lj + 0.5 * (v0 * v0 + v1 * v1))), v0, v1)
            ta, tdec = (vp - v0) / a, (vp - v1) / a
            da, dd = (vp * vp - v0 * v0) / (2 * a), (vp * vp - v1 * v1) / (2 * a)
            tc = max(Lj - da - dd, 0.0) / vp
            for T, v_start, acc, s0 in ((ta, v0, a, ks[j - 1]), (tc, vp, 0.0, ks[j - 1] + da),
                                        (tdec, vp, -a, ks[j] - dd)):
                if T > 0.0:
                    ph[n, 0], ph[n, 1], ph[n, 2], ph[n, 3] = t, owner[j], s0, v_start
                    ph[n, 4], ph[n, 5], ph[n, 6] = acc, 0.0, T
                    n += 1
                    t += T
        if i < 0:
            continue
        if i > 0 and not moving[i]:
            T = 1.5 * ang[i] / max_reorient
            ph[n, 0], ph[n, 1], ph[n, 2], ph[n, 5], ph[n, 6] = t, i, ks[j], 2.0, T
            n += 1
            t += T
        arrive[i] = t
        if dwell_k[i] > 0:
            ph[n, 0], ph[n, 1], ph[n, 2], ph[n, 5], ph[n, 6] = t, i, ks[j], 1.0, dwell_k[i]
            n += 1
            t += dwell_k[i]
        depart[i] = t
    if n == 0:
        n = 1  # a single point: one empty dwell phase
        ph[0, 5] = 1.0
    return ph[:n], arrive, depart, t


@njit(cache=True)
def look_ahead(v: np.ndarray, L: np.ndarray, a: float) -> np.ndarray:
    """Cap knot speeds ``v`` so each is reachable from and brakeable to its neighbours."""
    v = v.copy()
    for i in range(v.size - 2, -1, -1):
        v[i] = min(v[i], math.sqrt(v[i + 1] * v[i + 1] + 2.0 * a * L[i + 1]))
    for i in range(1, v.size):
        v[i] = min(v[i], math.sqrt(v[i - 1] * v[i - 1] + 2.0 * a * L[i]))
    return v
