"""The closed loop on the twin: a layer's toolpath asked for as the layer begins to spray.

The driver's ``next_layer(layer)`` answers with the whole toolpath as it now stands (its
layer ``layer`` corrected, the geometry as programmed) or None (as it was). The new toolpath
is executed from the start with the robot's own dynamics (:func:`twin.cell.motion.
execute_toolpath`): where the layer's approach ends in a stop (the pause between layers,
``Simulation(layer_pause_s=...)``), nothing before it depends on the speeds that follow, so
the motion up to there is the motion the stream already gave, sample for sample (checked),
and the stream goes on with the new motion from that sample.
"""

from __future__ import annotations

import logging
from collections.abc import Callable

import numpy as np

from dm2.core.messages import Toolpath

log = logging.getLogger(__name__)

NextLayer = Callable[[int], Toolpath | None]


class Replanner:
    """Asks ``next_layer`` once per layer and executes the answer on ``sim``'s cell."""

    def __init__(self, sim, next_layer: NextLayer):
        self.sim = sim
        self.next_layer = next_layer
        self.asked: set[int] = set()
        self.replanned: list[int] = []  # layers executed with a new toolpath

    def at_layer(self, layer: int, motion, a: int):
        """The new motion for ``layer``, whose first spraying chunk starts at sample ``a``,
        or None (no new toolpath, or asked already)."""
        from twin.cell.motion import execute_toolpath

        if layer in self.asked:
            return None
        self.asked.add(layer)
        toolpath = self.next_layer(layer)
        if toolpath is None:
            return None
        sim = self.sim
        new = execute_toolpath(toolpath, sim.cell, rate_hz=sim.cell.robot_state_hz,
                               accel_mm_s2=sim.cell.accel_mm_s2, dwell=sim.dwell_for(toolpath))
        if (new.t_s.size < a or not np.array_equal(new.t_s[:a], motion.t_s[:a])
                or not np.array_equal(new.joints_rad[:a], motion.joints_rad[:a])):
            raise RuntimeError(f"layer {layer}: the corrected toolpath changes the motion "
                               "already executed (no stop before the layer sprays)")
        sc = sim.scenario
        sim.end_s = (float(new.t_s[-1]) if sc.duration_s is None
                     else min(float(new.t_s[-1]), float(sc.duration_s)))
        self.replanned.append(layer)
        log.info("layer %d: executing the corrected speeds", layer)
        return new

    @staticmethod
    def chunk_at(chunks: list, trig_end: list, a: int, k: int) -> int:
        """The index of the new chunk that starts at sample ``a`` (its triggers from ``k``)."""
        starts = [c0 for c0, _ in chunks]
        c = int(np.searchsorted(starts, a))
        if c >= len(chunks) or starts[c] != a or (trig_end[c - 1] if c else 0) != k:
            raise RuntimeError(f"the new motion has no chunk starting at sample {a}")
        return c
