"""When a layer's process fit reaches the reference: at a fixed point of the stream.

The analysis of each closed layer proposes a process fit (:class:`~dm2.process.process_fit.
ProcessFit`: the deposition scale from here, the rescale of what the reference already holds, the
plume width, and the model-error factors the layer measured). Were it applied the moment the
analysis ends, the reference would change at a point of the stream that depends on whether the
analysis ran inline or on the worker thread. :class:`FitSchedule` holds the proposal until the
robot states up to ``FIT_APPLY_DELAY_S`` of stream time past the layer's close are integrated,
or the next layer closes, whichever comes first, and applies it there: the same results either
way. While a layer may calibrate the process, its top seen again until then
(:class:`~dm2.process.reobserved_top.ReobservedTop`) gives the calibration when enough of it
was seen.
"""

from __future__ import annotations

from dm2.defects.uncertainty_online import live_factors
from dm2.process.reobserved_top import ReobservedTop

FIT_APPLY_DELAY_S = 5.0  # [s] stream time after a layer's close its process fit applies at


class FitSchedule:
    """The pending process fit of a session and where in the stream it applies.

    Parameters
    ----------
    process_fit : the session's :class:`~dm2.process.process_fit.ProcessFit`, or None (then
        nothing is ever pending)
    reference, seen, grown, realtime : the session's near-net reference, seen reference, grown
        columns and real-time deviation, which a fit rescales
    """

    def __init__(self, process_fit, reference, seen, grown, realtime):
        self.process_fit = process_fit
        self.reference, self.seen, self.grown, self.realtime = reference, seen, grown, realtime
        self.worker = None  # the session's layer worker, when it has one
        self.pending: tuple | None = None  # (scale, rescale, plume, inflation)
        self.reobserved: ReobservedTop | None = None  # the calibration layer seen again
        self.due_s: float | None = None  # stream time the pending fit is applied at

    def layer_taken(self, ref, stamp_s: float) -> None:
        """A layer that closed at ``stamp_s`` (its reference ``ref``) goes to its analysis: its
        fit is due ``FIT_APPLY_DELAY_S`` later; a layer that may calibrate watches its top."""
        if self.process_fit is None:
            return
        self.due_s = stamp_s + FIT_APPLY_DELAY_S
        if self.process_fit.calibrating:
            self.reobserved = ReobservedTop(ref, stamp_s, self.due_s)

    def observe(self, points_O, stamp_s: float, heights_mm) -> None:
        """Profile points seen at ``stamp_s``: the calibration layer's top, seen again."""
        if self.reobserved is not None:
            self.reobserved.observe(points_O, stamp_s, heights_mm)

    def analysed(self, result) -> None:
        """The fit proposed by an analysed layer (a ``LayerResult``), with the model-error
        factors it measured (for the real-time columns); applied at :meth:`apply`."""
        if self.process_fit is not None:
            self.pending = (*self.process_fit.update(result), result.deviation.model_inflation)

    def apply(self, analysed_to: int) -> None:
        """Apply the fit of the layer analysed last (``analysed_to``): the reference deposits
        at the fitted scale from here, and at the calibration (measured on the top seen again,
        if enough was) what it holds, its layers not yet analysed and the seen reference are
        scaled and widened."""
        self.due_s = None
        if self.worker is not None:
            self.worker.join()  # the previous layer's analysis (it had FIT_APPLY_DELAY_S)
        pending, self.pending = self.pending, None
        top, self.reobserved = self.reobserved, None
        if pending is None:
            return
        if top is not None:  # a calibration: from the top seen again, if enough was
            again = self.process_fit.recalibrate(top)
            pending = pending if again is None else (*again, pending[3])
        scale, rescale, plume, inflation = pending
        self.realtime.set_model_inflation(live_factors(inflation))
        self.reference.set_process_scale(scale, rescale, analysed_to=analysed_to)
        self.seen.calibrated(self.reference, rescale, plume)
        self.grown.calibrated(self.reference.heights_mm, rescale, plume)
