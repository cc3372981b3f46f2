"""The closed loop: the measured top against the planned next layer gives per-segment speeds."""

from dm2.control.law import LayerCorrection, correct_layer
from dm2.control.top_map import TopMap, measured_top

__all__ = ["LayerCorrection", "TopMap", "correct_layer", "measured_top"]
