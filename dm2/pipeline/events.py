"""The typed steps a :class:`dm2.pipeline.session.MonitoringSession` runs in stream order
(layer marks, closed layers, what the profiles saw), and its per-stage timing."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from dm2.fusion.fusion import LayerSurface


@dataclass(frozen=True)
class LayerStarted:
    """The stream's mark that layer ``layer`` starts at ``stamp_s``: the reference of
    ``layer - 1`` is complete once the robot states up to the mark are integrated."""

    stamp_s: float
    layer: int


@dataclass(frozen=True)
class Observed:
    """The fusion fused a profile stamped ``stamp_s`` that saw the surface at ``points_O
    (n, 3)`` [mm]: the reference there, once integrated up to ``stamp_s``, is what it saw."""

    stamp_s: float
    points_O: np.ndarray


@dataclass(frozen=True)
class LayerClosed:
    """The fusion closed a layer (its last profile at ``stamp_s``; inf: at the end of the
    stream): take that layer's reference and hand the layer to the analysis."""

    stamp_s: float
    layer_surface: LayerSurface


@dataclass
class SessionTiming:
    """Wall seconds spent per stage, summed over the run."""

    fusion_s: float = 0.0
    reference_s: float = 0.0
    analysis_s: float = 0.0
    realtime_s: float = 0.0
    messages: int = 0
    extra: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return {"fusion_s": self.fusion_s, "reference_s": self.reference_s,
                "analysis_s": self.analysis_s, "realtime_s": self.realtime_s,
                "messages": self.messages, **self.extra}
