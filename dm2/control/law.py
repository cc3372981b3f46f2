"""The correction law: per segment of the next layer, a traverse-speed factor.

The law
-------
A Gaussian track sprayed at constant powder feed ``m`` [g/s] and traverse speed ``v`` lays
down a cross-section ``A = m * zeta / (rho * v)``: the deposit's height at a spot is
proportional to ``1 / v`` (the plume's width and the efficiency do not change with ``v``).
Where the programmed speed ``v_p`` lays one planned layer ``t`` (``[toolpath] layer_mm``),
``f * v_p`` lays ``t / f``: to lay ``t + e`` the nozzle moves at ``f = t / (t + e)`` times the
programmed speed.

After layer ``k`` the error ``e`` at a segment of layer ``k + 1`` is the planned surface that
segment sprays onto (its toolpath target ``z``, the design intent, never the online-fitted
reference) less the measured top there (averaged over the plume's width): ``e > 0``, the part
is short and the nozzle slows. The correction takes ``gain * e`` of it in one layer:
``f = t / (t + gain * e)``. The law is absolute, not incremental: the measured top already
holds what the earlier corrections did.

Then, in this order:

1. **Bounds**: ``min_speed_factor <= f <= max_speed_factor`` and ``f * v_p <= max_speed_mm_s``.
2. **Rate**: a spot's factor moves at most ``rate_per_layer`` from the factor the nearest
   segment of the layer before had (1 where it had none within ``NEIGHBOUR_MM``).
3. **Acceleration**: along each run of spray moves with the same programmed speed, speed
   changes fit the robot's path acceleration ``a``: a segment's higher speed is reached within
   its first half (``v_i^2 <= v_(i-1)^2 + a * len_i``), a lower one before the last half of the
   segment before it (``v_(i-1)^2 <= v_i^2 + a * len_(i-1)``). A forward and a backward pass
   only lower speeds, so the bounds keep holding; where they lower a factor by more than the
   rate limit, the acceleration wins (it is the robot's hard limit).

Assumptions: the feed is constant (no feed factor: a feed change reaches the nozzle seconds
later through the powder hose, so it cannot act per segment); the deposit of one pass spreads
over about the plume's width, so the error is read averaged over ``sample_sigma_mm``; the
deposition efficiency does not depend on speed. Segments with no measured top near them,
moves without spray and the programmed geometry are left as programmed: only ``speed_mm_s``
changes, rounded to the RAPID module's 0.001 mm/s.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial import cKDTree

from dm2.control.top_map import TopMap
from dm2.core.config import ControlConfig
from dm2.core.messages import Toolpath
from dm2.toolpath.formats import RAPID_SPEED_DECIMALS

NEIGHBOUR_MM = 5.0  # the previous layer's factor is read from its nearest segment this close


@dataclass(frozen=True)
class LayerCorrection:
    """The correction of one layer, per toolpath row of that layer (the move into the row).

    layer : int, the layer corrected (the one about to be sprayed)
    rows : (m,) int64, the rows of the full toolpath
    midpoint_O : (m, 3) float64 [mm], the middle of each move
    spray_on : (m,) bool, the move sprays (only those are corrected)
    error_mm : (m,) float64 [mm], planned surface minus measured top, + short; NaN unmeasured
    target : (m,) float64, the law's factor before bounds, rate and acceleration
    factor : (m,) float64, commanded over programmed speed
    programmed_mm_s, speed_mm_s : (m,) float64 [mm/s]
    """

    layer: int
    rows: np.ndarray
    midpoint_O: np.ndarray
    spray_on: np.ndarray
    error_mm: np.ndarray
    target: np.ndarray
    factor: np.ndarray
    programmed_mm_s: np.ndarray
    speed_mm_s: np.ndarray

    def summary(self) -> dict:
        """The layer's figures for ``report.json``."""
        on = self.spray_on
        f, e = self.factor[on], self.error_mm[on]
        seen = np.isfinite(e)
        return {"layer": self.layer, "segments": int(on.sum()),
                "measured_segments": int(seen.sum()),
                "mean_error_mm": float(np.mean(e[seen])) if seen.any() else None,
                "max_abs_error_mm": float(np.max(np.abs(e[seen]))) if seen.any() else None,
                "min_factor": float(f.min()) if f.size else 1.0,
                "mean_factor": float(f.mean()) if f.size else 1.0,
                "max_factor": float(f.max()) if f.size else 1.0,
                "slowed_segments": int(np.sum(f < 1.0 - 1e-9)),
                "sped_up_segments": int(np.sum(f > 1.0 + 1e-9))}


def law_factor(error_mm: np.ndarray, layer_mm: float, gain: float) -> np.ndarray:
    """``t / (t + gain * e)``; inf where the layer would have to lay nothing or less."""
    want = layer_mm + gain * np.asarray(error_mm, float)
    with np.errstate(divide="ignore"):
        return np.where(want > 0, layer_mm / np.maximum(want, 1e-300), np.inf)


def accel_limit(speed_mm_s: np.ndarray, length_mm: np.ndarray, run_start: np.ndarray,
                accel_mm_s2: float) -> np.ndarray:
    """Lower speeds so each change within a run fits the acceleration (see the module doc).

    speed_mm_s, length_mm : (m,) the moves' speeds and lengths; run_start : (m,) bool, a move
    that is not tied to the one before (a new run).
    """
    v = np.array(speed_mm_s, float)
    for i in range(1, len(v)):  # accelerate within the first half of move i
        if not run_start[i]:
            v[i] = min(v[i], np.sqrt(v[i - 1] ** 2 + accel_mm_s2 * length_mm[i]))
    for i in range(len(v) - 1, 0, -1):  # decelerate within the last half of move i - 1
        if not run_start[i]:
            v[i - 1] = min(v[i - 1], np.sqrt(v[i] ** 2 + accel_mm_s2 * length_mm[i - 1]))
    return v


def _previous_factor(mid_O: np.ndarray, previous: LayerCorrection | None) -> np.ndarray:
    if previous is None or not previous.spray_on.any():
        return np.ones(len(mid_O))
    on = previous.spray_on
    d, k = cKDTree(previous.midpoint_O[on, :2]).query(mid_O[:, :2])
    return np.where(d <= NEIGHBOUR_MM, previous.factor[on][np.minimum(k, on.sum() - 1)], 1.0)


def correct_layer(toolpath: Toolpath, layer: int, top: TopMap, cfg: ControlConfig,
                  layer_mm: float, previous: LayerCorrection | None = None
                  ) -> tuple[Toolpath, LayerCorrection]:
    """The toolpath with ``layer``'s speeds corrected from the measured ``top``, and the
    correction. ``previous``: the correction of the layer before (for the rate limit)."""
    rows = np.flatnonzero(toolpath.layer == layer)
    if rows.size == 0:
        raise ValueError(f"correct_layer: the toolpath has no layer {layer}")
    pos = toolpath.position_O
    before = pos[np.maximum(rows - 1, 0)]
    mid = 0.5 * (before + pos[rows])
    length = np.linalg.norm(pos[rows] - before, axis=1)
    spray = toolpath.spray_on[rows].copy()
    spray[0] &= rows[0] > 0 and toolpath.layer[rows[0] - 1] == layer  # the move in from below
    v_p = toolpath.speed_mm_s[rows]
    error = pos[rows, 2] - top.sample(mid, cfg.sample_sigma_mm)
    target = np.where(spray & np.isfinite(error), law_factor(np.nan_to_num(error), layer_mm,
                                                             cfg.gain), 1.0)
    hi = np.minimum(cfg.max_speed_factor, cfg.max_speed_mm_s / v_p)
    f = np.clip(target, cfg.min_speed_factor, hi)
    prev = _previous_factor(mid, previous)
    f = np.clip(f, prev - cfg.rate_per_layer, prev + cfg.rate_per_layer)
    f = np.clip(f, cfg.min_speed_factor, hi)
    f = np.where(spray, f, 1.0)
    tied = spray & np.r_[False, spray[:-1]] & np.r_[False, v_p[1:] == v_p[:-1]]
    # to the speeddata's precision, so a RAPID module commands exactly these speeds
    v = np.round(accel_limit(f * v_p, length, ~tied, cfg.accel_mm_s2), RAPID_SPEED_DECIMALS)
    speed = toolpath.speed_mm_s.copy()
    speed[rows] = v
    corrected = replace(toolpath, speed_mm_s=speed)
    return corrected, LayerCorrection(layer, rows, mid, spray, np.where(spray, error, np.nan),
                                      target, v / v_p, v_p, v)
