"""A session's real-time comparison: one per fused frame set, its alarms logged, its latency kept.

After every fused frame set the session compares the active region of the measured TSDF with
the reference as of the newest fused profile (:class:`~dm2.defects.realtime.RealtimeDeviation`).
:class:`RealtimeStage` runs that comparison at the spray spot of the newest robot state, writes
each alarm to the ``dm2.alarms`` log (the run's log file, not the console) and keeps the
per-frame-set latency for the report.
"""

from __future__ import annotations

import logging
import time

import numpy as np

alarm_log = logging.getLogger("dm2.alarms")  # real-time alarms: the log file, not the console


class RealtimeStage:
    """Real-time comparisons of one session (``deviation``: its
    :class:`~dm2.defects.realtime.RealtimeDeviation`)."""

    def __init__(self, deviation):
        self.deviation = deviation
        self.latency_s: list[float] = []

    def compare(self, tsdf, reference, T_B_F, stamp_s: float) -> float:
        """Compare the active region around the spray spot of flange pose ``T_B_F`` with
        ``reference`` at ``stamp_s``; returns the seconds it took."""
        t0 = time.perf_counter()
        spot_O, _ = reference.spot_O(T_B_F)
        frame = self.deviation.update_from_tsdf(tsdf, spot_O, stamp_s, reference)
        for alarm in frame.alarms:
            alarm_log.info("real-time: %s of %.1f mm2 at (%.1f, %.1f) mm, %.2f s after its first "
                           "flag", alarm.kind, alarm.area_mm2, *alarm.centroid_xy_O,
                           alarm.stamp_s - alarm.first_flag_s)
        dt = time.perf_counter() - t0
        self.latency_s.append(dt)
        return dt

    def summary(self) -> dict:
        """Real-time deviation alarms and per-frame-set latency, for the report."""
        lat = np.asarray(self.latency_s)
        return {
            "frame_sets": int(lat.size),
            "latency_ms_p50": float(np.percentile(lat, 50) * 1e3) if lat.size else None,
            "latency_ms_p99": float(np.percentile(lat, 99) * 1e3) if lat.size else None,
            "alarms": [{"stamp_s": a.stamp_s, "kind": a.kind, "area_mm2": a.area_mm2,
                        "centroid_xy_O_mm": [float(c) for c in a.centroid_xy_O],
                        "first_flag_s": a.first_flag_s,
                        "delay_s": a.stamp_s - a.first_flag_s}
                       for a in self.deviation.alarms],
        }
