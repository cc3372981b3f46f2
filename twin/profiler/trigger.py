"""The cascaded trigger box of the three profilers: profile stamps, sensors and counters."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from dm2.core.config import SensorConfig
from dm2.core.messages import COUNTER_MODULO, SENSOR_IDS


def trigger_schedule(t_end_s: float, sensors: SensorConfig, t0_s: float = 0.0,
                     start_counter: int | Sequence[int] = 0
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Profile stamps of the cascaded trigger box from ``t0_s`` up to ``t_end_s`` inclusive.

    Trigger ``k`` fires sensor ``j`` at ``t0_s + k / rate_hz + j * cascade_s``; each sensor's
    24-bit counter is ``(start_counter[j] + k) mod 2**24``.

    Returns
    -------
    stamps_s : (m,) float64 [s], ascending
    sensor_index : (m,) int64, index into ``SENSOR_IDS``
    counter : (m,) int64
    """
    n_sensors = len(SENSOR_IDS)
    starts = np.broadcast_to(np.asarray(start_counter, dtype=np.int64), (n_sensors,))
    if np.any(starts < 0):
        raise ValueError(f"trigger_schedule: start_counter must be >= 0, got {start_counter}")
    if not np.isfinite(t_end_s) or t_end_s < t0_s:
        return np.zeros(0), np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    n_trig = int(np.floor((t_end_s - t0_s) * sensors.rate_hz)) + 2
    k = np.repeat(np.arange(n_trig, dtype=np.int64), n_sensors)
    j = np.tile(np.arange(n_sensors, dtype=np.int64), n_trig)
    stamps = t0_s + k / sensors.rate_hz + j * sensors.cascade_s
    keep = stamps <= t_end_s
    stamps, k, j = stamps[keep], k[keep], j[keep]
    order = np.argsort(stamps, kind="stable")
    counter = (starts[j] + k) % COUNTER_MODULO
    return stamps[order], j[order], counter[order]
