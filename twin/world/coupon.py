"""The deposition scale a scenario's twin really deposits at, its efficiency curve included.

The scale a process finding is scored against (dm2.bench.scoring: an ``offset`` finding on a
control is correct within 3 % of it) has two parts:

* the **factors** of ``[twin_process]``: feed x normal-impact efficiency against the nominal
  ``[process]``, over the dense fraction ``1 - porosity`` (the deposit stands taller by its
  pores). Mass conservation makes this exact for any plume width or shape;
* what the twin's **efficiency curve** takes at normal spray. The jet diverges and the deposit
  ripples, so packets meet even a flat plate a few degrees off normal: the default ``plateau``
  curve, flat to 30 deg, loses nothing there, a ``linear`` one (``1 - theta / theta_c``) loses
  about 5 %. That part is measured as a shop measures a cell's efficiency: a flat raster coupon
  sprayed at normal incidence (:func:`coupon_plateau_mm`), once with the scenario's curve and once
  with a curve flat to its plateau angle, same seed and packets, and the ratio of the two
  plateaus' median heights.

So a twin whose curve is flat near normal incidence gets the factors exactly, and the linear
curve's twin of the default physics gets 0.899 instead of the factors' 0.949 (its own first
layer on the part reads 0.894).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from twin.world.deposition import SprayModel, twin_process
from twin.world.heightfield import HeightField
from twin.world.twin_physics import TwinPhysics

COUPON_MM = 40.0  # side of the sprayed square [mm], at least (wider for a wide plume)
PLATEAU_LINES = 5  # raster lines the plateau spans, at least
CELL_MM = 0.25
RATE_HZ = 250.0  # motion samples per second, as the robot state stream
PLATEAU_MARGIN_SIGMAS = 4.0  # the plateau is this many plume sigmas inside the raster
FLAT_CURVE = "plateau"  # the curve that takes nothing at normal spray (flat to its angle)


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


def coupon_plateau_mm(process, physics: TwinPhysics, spacing_mm: float, speed_mm_s: float,
                      seed: int) -> float:
    """Median plateau height [mm] of one raster layer sprayed at normal incidence on a flat
    plate, at least :data:`COUPON_MM` wide (wider where a wide plume needs it for a plateau of
    :data:`PLATEAU_LINES` lines, :data:`PLATEAU_MARGIN_SIGMAS` sigmas inside the edges)."""
    model = SprayModel(process, seed=seed, physics=physics)
    margin = PLATEAU_MARGIN_SIGMAS * model.sigma_mm()
    side = max(COUPON_MM, 2.0 * margin + PLATEAU_LINES * spacing_mm)
    # the plume's tails stay on the plate; whole mm, so the raster sits on the cells alike
    plate = float(np.ceil(side + 2.0 * margin + 2.0 * spacing_mm))
    centre = 0.5 * plate
    spots = raster_spots(side, spacing_mm, speed_mm_s, centre)
    axes = np.tile([0.0, 0.0, -1.0], (len(spots), 1))
    hf = HeightField((plate, plate), CELL_MM, 6.0)
    model.deposit_samples(hf, spots, axes, 1.0 / RATE_HZ)
    inner = 0.5 * side - margin
    ny, nx = hf.heights_mm.shape
    x = (np.arange(nx) + 0.5) * CELL_MM - centre
    y = (np.arange(ny) + 0.5) * CELL_MM - centre
    plateau = (np.abs(x)[None, :] <= inner) & (np.abs(y)[:, None] <= inner)
    return float(np.median(hf.heights_mm[plateau]))


def coupon_scale(scenario) -> float:
    """The twin's deposition scale against the nominal ``[process]``: the factors times what
    its efficiency curve takes on a flat coupon (see the module docstring)."""
    proc, physics = twin_process(scenario)
    nominal = scenario.process
    factors = (proc.feed_g_min * proc.deposition_efficiency
               / (nominal.feed_g_min * nominal.deposition_efficiency)
               / (1.0 - physics.porosity) * nominal.powder_density_g_cm3
               / proc.powder_density_g_cm3)
    if physics.efficiency_curve == FLAT_CURVE and physics.efficiency_cos_exponent == 0.0:
        return float(factors)
    flat = replace(physics, efficiency_curve=FLAT_CURVE, efficiency_cos_exponent=0.0)
    args = (float(scenario.toolpath.line_spacing_mm), float(scenario.toolpath.speed_mm_s.infill),
            int(scenario.seed))
    curve = coupon_plateau_mm(proc, physics, *args) / coupon_plateau_mm(proc, flat, *args)
    return float(factors * curve)
