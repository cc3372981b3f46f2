"""The process fit: the deposition model follows the cell (paper section 6.1's reference, fitted).

The first layer calibrates the deposition scale and the plume width on the part's own top
(:mod:`~dm2.process.process_fit`, :mod:`~dm2.process.process_top`, measured again on the top
the profilers see once the next layer has begun, :mod:`~dm2.process.reobserved_top`); then a
rate-limited follower reads each layer's growth at its own top vertices
(:mod:`~dm2.process.calibration_top`). :mod:`~dm2.process.fit_schedule` applies each fit at a
fixed point of the stream. It sits between the defects (whose classes it reads) and the
pipeline (which runs it).
"""
