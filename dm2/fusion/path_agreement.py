"""Whether a recording's robot followed a toolpath, over the whole run.

The spray spot of every recorded robot state (the point ``standoff_mm`` along the nozzle
axis, in ``O``) is compared with the toolpath polyline. The run is cut into windows of
``WINDOW_S`` of stream time; in every window where the spot moved at least ``MIN_TRAVEL_MM``
(a robot standing still at home or waiting is not following any path), the median distance
from the spot to the toolpath must be at most ``MAX_MEDIAN_MM``. The first window that
departs further names where the recording and the toolpath part: its time and the layer
there (the recording's own layer marks where it has them, else the toolpath layer nearest to
the spot).

The bound is the registration's own scale: a toolpath off by more than 3 mm puts the
reference's deposit beside the measured one, which the deviation analysis would take for
an over- and an underbuild.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

MAX_MEDIAN_MM = 3.0  # median spot-to-toolpath distance allowed in a window of motion
WINDOW_S = 1.0  # [s] of stream time per window
MIN_TRAVEL_MM = 1.0  # a window in which the spot moved less is not judged


@dataclass(frozen=True)
class Departure:
    """Where the executed path and the toolpath part.

    Attributes
    ----------
    start_s, end_s : float [s], the window (stamps of its first and last robot state)
    median_mm : float [mm], the spot's median distance from the toolpath there
    layer : int, the layer there: the recording's (its last layer mark before ``start_s``)
        where it has layer marks, else the toolpath layer nearest to the spot (most frequent)
    windows : int, windows of motion judged in all
    layer_source : "layer marks" or "nearest toolpath layer"
    """

    start_s: float
    end_s: float
    median_mm: float
    layer: int
    windows: int
    layer_source: str = "nearest toolpath layer"

    def where(self) -> str:
        """``"3.0 s (layer 0 by the recording's layer marks)"``."""
        src = ("by the recording's layer marks" if self.layer_source == "layer marks"
               else "the nearest toolpath layer")
        return f"{self.start_s:.1f} s (layer {self.layer}, {src})"


def executed_spots(rec, cal, standoff_mm: float):
    """``(stamps (n,) [s], spots (n, 3) in O [mm], layer marks [(stamp_s, layer)])`` of every
    robot state of ``rec``: through its own ``robot_poses()`` and ``layer_marks()`` where it
    has them (only those records decoded), else through its messages."""
    from dm2.core.frames import invert
    from dm2.core.messages import LayerMark, RobotState
    from dm2.fusion.registration import spot_B

    spot = spot_B(cal, standoff_mm)
    marks: list[tuple[float, int]] = []
    if hasattr(rec, "robot_poses"):
        poses = rec.robot_poses()
        marks = list(rec.layer_marks())
    else:
        def poses_of(msgs):
            for m in msgs:
                if isinstance(m, RobotState):
                    yield m.stamp_s, m.T_B_F
                elif isinstance(m, LayerMark):
                    marks.append((m.stamp_s, m.layer))
        poses = poses_of(rec.messages())
    stamps, spots = [], []
    for stamp_s, T_B_F in poses:
        T_O_B = invert(T_B_F @ cal.T_F_O)
        stamps.append(stamp_s)
        spots.append(T_O_B[:3, :3] @ spot + T_O_B[:3, 3])
    order = np.argsort(stamps, kind="stable")
    return (np.asarray(stamps, float)[order], np.asarray(spots, float).reshape(-1, 3)[order],
            sorted(marks))


def first_departure(stamps_s: np.ndarray, spots_O: np.ndarray, toolpath, *, marks=(),
                    max_median_mm: float = MAX_MEDIAN_MM, window_s: float = WINDOW_S,
                    min_travel_mm: float = MIN_TRAVEL_MM) -> Departure | None:
    """The first window of motion whose spots lie a median beyond ``max_median_mm`` from the
    toolpath, or None when the whole run follows it (``marks``: the recording's layer marks,
    ``(stamp_s, layer)`` in stamp order, to name the layer there)."""
    from scipy.spatial import cKDTree

    from dm2.fusion.layers import resample_toolpath

    if len(stamps_s) == 0:
        return None
    pts, layers = resample_toolpath(toolpath, spacing_mm=0.5)
    if len(pts) == 0:
        return None
    dist, idx = cKDTree(pts).query(spots_O)
    step = np.r_[0.0, np.linalg.norm(np.diff(spots_O, axis=0), axis=1)]
    win = np.floor((stamps_s - stamps_s[0]) / window_s).astype(np.int64)
    bounds = np.flatnonzero(np.r_[True, np.diff(win) != 0, True])
    judged = 0
    for a, b in zip(bounds[:-1], bounds[1:], strict=True):
        if step[a + 1:b].sum() < min_travel_mm:
            continue
        judged += 1
        med = float(np.median(dist[a:b]))
        if med > max_median_mm:
            t0 = float(stamps_s[a])
            before = [layer for stamp, layer in marks if stamp <= t0]
            if before:
                return Departure(t0, float(stamps_s[b - 1]), med, int(before[-1]), judged,
                                 "layer marks")
            near = np.bincount(layers[idx[a:b]] - layers.min())
            return Departure(t0, float(stamps_s[b - 1]), med,
                             int(np.argmax(near) + layers.min()), judged)
    return None
