"""What is not surface, taken out of each profile before fusion.

A laser profiler on a cold-spray cell returns, besides the surface, single points and short
stretches that lie well off it: multiple reflections (ghosts behind the surface), powder
particles crossing the laser sheet (points in front of it), and bursts where a whole stretch
of the line is misread at once. Fused as they are, each carves free space through the true
surface along its ray (a ghost) or adds material in front of it (a particle).

:func:`line_outliers` finds them along the profile line. A run of at most ``max_run``
consecutive points is rejected when every point of it lies more than ``reject_mm`` off the
straight line fitted (total least squares) to the three points on each side of it, and those
six agree on that line: all of them, or all but one, lie within ``agree_mm`` of it. The points
on each side must be one stretch of the line, at most ``max_step_mm`` apart in x, and the run
no wider than its place between them: where a profile comes in fragments (occlusions, grazing
walls) no line is trusted across a gap. On a surface the TSDF can resolve (0.5 mm voxels
against 0.08 mm between points) no point lies that far off a line its neighbours agree on;
at an edge or a corner the neighbours do not agree on one line, so nothing there is
rejected. Points within three of a profile's ends are never tested. Only a run entered and
left by a jump of more than ``reject_mm - agree_mm / 2`` between neighbours, whose first point
lies that far off the chord across it, is fitted at all (a clean profile has few, so it costs
about a pass over its points).

:class:`PointFilter` applies it to a batch of profiles and counts what it took out, by
reason and by sensor (report.json ``point_filter``).
"""

from __future__ import annotations

import numpy as np
from numba import njit

KEEP = 0
SINGLE = 1  # one point off the line its neighbours agree on
BURST = 2  # a run of 2..max_run consecutive points off it
REASONS = {SINGLE: "single", BURST: "burst"}
SIDE = 3  # points tried on each side of a run
# the gap across a run along the line is at most this many times its length in steps
GAP_SLACK = 2.5


@njit(cache=True, nogil=True)
def _jump(xz, q):
    """Distance [mm] from point ``q`` to point ``q + 1``."""
    dx = xz[q + 1, 0] - xz[q, 0]
    dz = xz[q + 1, 1] - xz[q, 1]
    return np.sqrt(dx * dx + dz * dz)


@njit(cache=True, nogil=True)
def _off_chord(xz, j, k, p):
    """Distance [mm] of point ``p`` from the line through points ``j`` and ``k``."""
    dx = xz[k, 0] - xz[j, 0]
    dz = xz[k, 1] - xz[j, 1]
    norm = np.sqrt(dx * dx + dz * dz)
    if norm == 0.0:
        return 0.0
    return abs((xz[p, 0] - xz[j, 0]) * dz - (xz[p, 1] - xz[j, 1]) * dx) / norm


@njit(cache=True, nogil=True)
def _fit_line(xz, idx, m, skip):
    """``(cx, cz, nx, nz)``: the total-least-squares line (centroid, unit normal) through the
    points ``xz[idx[:m]]`` but ``idx[skip]`` (``skip = -1``: all)."""
    cx = cz = 0.0
    c = 0
    for t in range(m):
        if t != skip:
            cx += xz[idx[t], 0]
            cz += xz[idx[t], 1]
            c += 1
    cx /= c
    cz /= c
    sxx = sxz = szz = 0.0
    for t in range(m):
        if t != skip:
            dx = xz[idx[t], 0] - cx
            dz = xz[idx[t], 1] - cz
            sxx += dx * dx
            sxz += dx * dz
            szz += dz * dz
    # the normal is the direction of least spread: angle of the principal axis plus 90 deg
    theta = 0.5 * np.arctan2(2.0 * sxz, sxx - szz)
    return cx, cz, -np.sin(theta), np.cos(theta)


@njit(cache=True, nogil=True)
def _run_is_off(xz, i, r, a, b, reject_mm, agree_mm, max_step_mm, idx):
    """Whether the run ``i .. i + r - 1`` lies more than ``reject_mm`` off the line fitted to
    the ``SIDE`` points on each side of it (all of them, or all but one, within ``agree_mm`` of
    it), the points on each side one stretch of the line (at most ``max_step_mm`` apart in x)
    and the run no wider than its place between them."""
    lo, hi = i - SIDE, i + r + SIDE
    if lo < a or hi > b:
        return False
    if abs(xz[i + r, 0] - xz[i - 1, 0]) > max_step_mm * (r + 1):
        return False
    m = 0
    for q in range(lo, hi):
        if q < i or q >= i + r:
            if q + 1 < hi and q != i - 1 and abs(xz[q + 1, 0] - xz[q, 0]) > max_step_mm:
                return False
            idx[m] = q
            m += 1
    skip = -1
    for _attempt in range(2):
        cx, cz, nx, nz = _fit_line(xz, idx, m, skip)
        worst, worst_t = 0.0, -1
        for t in range(m):
            if t != skip:
                d = abs((xz[idx[t], 0] - cx) * nx + (xz[idx[t], 1] - cz) * nz)
                if d > worst:
                    worst, worst_t = d, t
        if worst <= agree_mm:
            # the run fills its place on the line: the gap across it is about its length in
            # steps between the points around it (two compact clusters also fit one line)
            step = 0.0
            steps = 0
            prev = -1
            for t in range(m):
                if t != skip:
                    if prev >= 0 and idx[prev] + 1 == idx[t]:
                        step += abs((xz[idx[t], 0] - xz[idx[prev], 0]) * nz
                                    - (xz[idx[t], 1] - xz[idx[prev], 1]) * nx)
                        steps += 1
                    prev = t
            gap = abs((xz[i + r, 0] - xz[i - 1, 0]) * nz - (xz[i + r, 1] - xz[i - 1, 1]) * nx)
            if steps <= 0 or gap > GAP_SLACK * (r + 1) * step / steps + 0.5 * agree_mm:
                return False
            for p in range(i, i + r):
                if abs((xz[p, 0] - cx) * nx + (xz[p, 1] - cz) * nz) <= reject_mm:
                    return False
            return True
        if idx[worst_t] == i - 1 or idx[worst_t] == i + r:
            return False  # the run's own neighbour is off: the run is longer, or no run
        skip = worst_t
    return False


@njit(cache=True, nogil=True)
def line_outliers(xz_S, offsets, reject_mm, agree_mm, max_step_mm, max_run, out_reason):
    """Mark, in ``out_reason (n,) int8``, the points of the profiles ``xz_S[offsets[j]:
    offsets[j + 1]]`` (float64 [mm, S], valid points in order along the line) that lie off
    the surface their neighbours agree on: ``SINGLE``, ``BURST`` or ``KEEP`` (see the module
    docstring). Shorter runs are tried first; a rejected run is skipped past."""
    out_reason[:] = KEEP
    idx = np.empty(2 * SIDE, dtype=np.int64)
    jump_mm = reject_mm - 0.5 * agree_mm
    for p in range(offsets.shape[0] - 1):
        a, b = offsets[p], offsets[p + 1]
        i = a + SIDE
        while i < b - SIDE:
            found = 0
            # a run starts with a jump off its left neighbour and ends with one back to its
            # right neighbour (screens before the fit: a clean profile has neither)
            if _jump(xz_S, i - 1) > jump_mm:
                for r in range(1, max_run + 1):
                    if i + r + SIDE > b:
                        break
                    if (_jump(xz_S, i + r - 1) > jump_mm
                            and _off_chord(xz_S, i - 1, i + r, i) > jump_mm
                            and _run_is_off(xz_S, i, r, a, b, reject_mm, agree_mm,
                                            max_step_mm, idx)):
                        found = r
                        break
            if found:
                code = SINGLE if found == 1 else BURST
                for q in range(i, i + found):
                    out_reason[q] = code
                i += found
            else:
                i += 1


@njit(cache=True, nogil=True)
def count_reasons(offsets, rows, reason, points, rejected):
    """Add each profile's points to ``points[rows[j]]`` and its rejected points to
    ``rejected[rows[j], reason]``; returns how many were rejected."""
    bad = 0
    for j in range(offsets.shape[0] - 1):
        points[rows[j]] += offsets[j + 1] - offsets[j]
        for q in range(offsets[j], offsets[j + 1]):
            if reason[q] != KEEP:
                rejected[rows[j], reason[q]] += 1
                bad += 1
    return bad


class PointFilter:
    """:func:`line_outliers` on each batch of profiles, with its counts.

    Parameters
    ----------
    reject_mm, agree_mm, max_step_mm, max_run : see :func:`line_outliers`
        (``[monitor.point_filter]``)
    sensor_ids : the sensors in the order of the batch's sensor rows

    Attributes
    ----------
    points : (sensors,) int64, points seen per sensor
    rejected : (sensors, reasons) int64, points rejected per sensor and reason
    layers : ``[(layer, points (sensors,), rejected (sensors,))]``: each finished layer's own
        counts (:meth:`close_layer`)
    """

    def __init__(self, reject_mm: float, agree_mm: float, max_step_mm: float, max_run: int,
                 sensor_ids):
        self.reject_mm = float(reject_mm)
        self.agree_mm = float(agree_mm)
        self.max_step_mm = float(max_step_mm)
        self.max_run = int(max_run)
        self.sensor_ids = list(sensor_ids)
        self.points = np.zeros(len(self.sensor_ids), dtype=np.int64)
        self.rejected = np.zeros((len(self.sensor_ids), len(REASONS) + 1), dtype=np.int64)
        self.layers: list[tuple[int, np.ndarray, np.ndarray]] = []
        self._at_close = (self.points.copy(), self.rejected.sum(axis=1))

    def close_layer(self, layer: int) -> None:
        """Keep what the layer ``layer`` that just finished saw and rejected, per sensor."""
        points, rejected = self.points.copy(), self.rejected.sum(axis=1)
        self.layers.append((int(layer), points - self._at_close[0],
                            rejected - self._at_close[1]))
        self._at_close = (points, rejected)

    def apply(self, xz_S: np.ndarray, offsets: np.ndarray, sensor_rows):
        """``(xz_S, offsets)`` of the batch with the rejected points taken out (the same
        arrays when none was)."""
        reason = np.empty(xz_S.shape[0], dtype=np.int8)
        line_outliers(xz_S, offsets, self.reject_mm, self.agree_mm, self.max_step_mm,
                      self.max_run, reason)
        rows = np.asarray(sensor_rows, dtype=np.int64)
        if not count_reasons(offsets, rows, reason, self.points, self.rejected):
            return xz_S, offsets
        keep = reason == KEEP
        kept_before = np.concatenate([[0], np.cumsum(keep)])
        return np.ascontiguousarray(xz_S[keep]), kept_before[offsets]

    def counts(self) -> dict[str, int]:
        """Rejected points by reason, all sensors (``point_filter_<reason>``, non-zero only)."""
        tot = self.rejected.sum(axis=0)
        return {f"point_filter_{name}": int(tot[code]) for code, name in REASONS.items()
                if tot[code]}

    def summary(self) -> dict:
        """report.json ``point_filter``: points seen and rejected by reason, per sensor, and
        per finished layer (``by_layer``: ``{"layer", "points": {sensor: n}, "rejected":
        {sensor: n}}``)."""
        per = {}
        for s, sid in enumerate(self.sensor_ids):
            n, rej = int(self.points[s]), self.rejected[s]
            per[sid] = {"points": n, "rejected": int(rej.sum()),
                        "share": float(rej.sum() / n) if n else 0.0,
                        **{name: int(rej[code]) for code, name in REASONS.items()}}
        n = int(self.points.sum())
        total = int(self.rejected.sum())
        return {"reject_mm": self.reject_mm, "max_run": self.max_run, "points": n,
                "rejected": total, "share": float(total / n) if n else 0.0,
                "by_sensor": per,
                "by_layer": [{"layer": layer,
                              "points": dict(zip(self.sensor_ids, pts.tolist(), strict=True)),
                              "rejected": dict(zip(self.sensor_ids, rej.tolist(), strict=True))}
                             for layer, pts, rej in self.layers]}
