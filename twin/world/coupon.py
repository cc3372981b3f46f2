"""The deposition scale a scenario's twin really deposits at: a flat raster coupon.

A cell's deposition efficiency is measured the way a shop measures it: spray a flat raster
coupon at normal incidence and compare its plateau with what the nominal process should give.
:func:`coupon_scale` does that on the twin: it deposits one raster layer with the scenario's
twin physics (``[twin_process]``: feed and efficiency factors, plume width and shape, porosity,
and the efficiency curve, which the jet's divergence samples at a few degrees off normal even on
a flat plate) and divides the plateau's median height by the nominal model's plateau, the
volume the nominal ``[process]`` sticks at normal incidence spread over the raster's speed x
line spacing.

This is the truth a process finding's deposition scale is scored against
(dm2.bench.scoring: an ``offset`` finding on a control is correct within 3 % of it). The plain
ratio of the factors (feed x efficiency / (1 - porosity)) misses what the curve takes: a twin
whose efficiency falls linearly from normal incidence deposits about 5 % less on a flat plate
than the factors say (0.899 against 0.949 with the default twin physics).
"""

from __future__ import annotations

import numpy as np

from twin.world.deposition import SprayModel, twin_process, volume_rate_mm3_s
from twin.world.heightfield import HeightField

COUPON_MM = 40.0  # side of the sprayed square [mm], at least (wider for a wide plume)
PLATEAU_LINES = 5  # raster lines the plateau spans, at least
CELL_MM = 0.25
RATE_HZ = 250.0  # motion samples per second, as the robot state stream
PLATEAU_MARGIN_SIGMAS = 4.0  # the plateau is this many plume sigmas inside the raster


def raster_spots(side_mm: float, spacing_mm: float, speed_mm_s: float,
                 centre_mm: float) -> np.ndarray:
    """Spray spots (m, 3) [mm] of a serpentine raster over a ``side_mm`` square centred at
    ``(centre_mm, centre_mm)`` on the plate (z = 0), sampled at :data:`RATE_HZ`."""
    lo, hi = centre_mm - 0.5 * side_mm, centre_mm + 0.5 * side_mm
    corners = []
    for k, y in enumerate(np.arange(lo, hi + 1e-9, spacing_mm)):
        corners += [(lo, y), (hi, y)] if k % 2 == 0 else [(hi, y), (lo, y)]
    corners = np.array(corners)
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(corners, axis=0), axis=1))])
    q = np.arange(0.0, s[-1], speed_mm_s / RATE_HZ)
    return np.column_stack([np.interp(q, s, corners[:, 0]), np.interp(q, s, corners[:, 1]),
                            np.zeros(q.size)])


def coupon_scale(scenario) -> float:
    """The twin's deposition scale against the nominal ``[process]`` (see the module
    docstring): the median plateau height of one raster coupon sprayed at normal incidence with
    the scenario's twin physics, over the nominal model's plateau height
    (the coupon is wider than :data:`COUPON_MM` where a wide plume needs it for a plateau)
    """
    proc, physics = twin_process(scenario)
    nominal = scenario.process
    spacing = float(scenario.toolpath.line_spacing_mm)
    speed = float(scenario.toolpath.speed_mm_s.infill)
    model = SprayModel(proc, seed=scenario.seed, physics=physics)
    margin = PLATEAU_MARGIN_SIGMAS * model.sigma_mm()
    side = max(COUPON_MM, 2.0 * margin + PLATEAU_LINES * spacing)
    # the plume's tails stay on the plate; whole mm, so the raster sits on the cells alike
    plate = float(np.ceil(side + 2.0 * margin + 2.0 * spacing))
    centre = 0.5 * plate
    spots = raster_spots(side, spacing, speed, centre)
    axes = np.tile([0.0, 0.0, -1.0], (len(spots), 1))
    hf = HeightField((plate, plate), CELL_MM, 6.0)
    model.deposit_samples(hf, spots, axes, 1.0 / RATE_HZ)
    inner = 0.5 * side - margin
    ny, nx = hf.heights_mm.shape
    x = (np.arange(nx) + 0.5) * CELL_MM - centre
    y = (np.arange(ny) + 0.5) * CELL_MM - centre
    plateau = (np.abs(x)[None, :] <= inner) & (np.abs(y)[:, None] <= inner)
    measured = float(np.median(hf.heights_mm[plateau]))
    expected = volume_rate_mm3_s(nominal) * nominal.deposition_efficiency / (speed * spacing)
    return measured / expected
