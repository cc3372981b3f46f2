"""The closed loop of a twin run (``--compensate``): the monitor's layers drive a
:class:`dm2.control.advisor.Compensator`; in "apply" mode the twin asks it for each layer's
toolpath as the layer begins to spray."""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path

log = logging.getLogger(__name__)

MODES = ("off", "advise", "apply", "hold")  # hold: apply's pauses, no correction (a baseline)


class ClosedLoop:
    """``on_layer`` for the pipeline (chained to ``user_on_layer``), ``next_layer`` for the
    twin (None unless "apply") and the report's ``control`` section."""

    def __init__(self, sim, scenario, mode: str, user_on_layer: Callable | None = None):
        if mode not in MODES:
            raise ValueError(f"--compensate: {mode!r} is not one of {', '.join(MODES)}")
        self.mode = mode
        self.user_on_layer = user_on_layer
        self.comp = None
        self.late: list[int] = []  # layers that began before their correction was ready
        self.sim = sim
        if mode in ("advise", "apply"):
            from dm2.control.advisor import Compensator

            self.comp = Compensator(sim.toolpath, scenario.control, scenario.toolpath.layer_mm)
        self.next_layer = self._next_layer if mode == "apply" else None

    def out_dir(self, path: Path) -> None:
        if self.comp is not None:
            self.comp.out_dir = Path(path)

    def on_layer(self, result) -> None:
        if self.comp is not None:
            self.comp.on_layer(result)
        if self.user_on_layer is not None:
            self.user_on_layer(result)

    def _next_layer(self, layer: int):
        if layer == 0:
            return None
        if layer not in self.comp.corrections:
            self.late.append(layer)
            log.warning("layer %d sprays as programmed: layer %d was not analysed in time",
                        layer, layer - 1)
            return None
        return self.comp.toolpath

    def sections(self) -> dict:
        """``{"control": ...}`` for report.json, or nothing when off."""
        if self.comp is None:
            return {}
        out = self.comp.summary(self.mode)
        if self.mode == "apply":
            out["late_layers"] = list(self.late)
            out["layer_pause_s"] = self.sim.layer_pause_s
        return {"control": out}
