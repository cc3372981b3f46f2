"""SprayModel on narrow features: a spike narrower than the normal's stencil does not capture
the jet (no needle), a pit reads flat and fills, and volume is kept exactly."""

from __future__ import annotations

import math

import numpy as np

from dm2.core.config import ProcessConfig
from twin.world import deposition_kernels as DK
from twin.world.deposition import SprayModel, plume_sigma_mm, volume_rate_mm3_s
from twin.world.heightfield import HeightField

CELL = 0.25


def _spike_field(width_cells: int, height_mm: float) -> tuple[HeightField, tuple[int, int]]:
    hf = HeightField(size_mm=(40.0, 40.0), cell_mm=CELL, thickness_mm=6.0)
    h = np.zeros_like(hf.heights_mm)
    c = h.shape[0] // 2
    lo, hi = c - width_cells // 2, c - width_cells // 2 + width_cells
    h[lo:hi, lo:hi] = height_mm
    hf.heights_mm = h
    return hf, (lo, hi)


def test_narrow_spike_under_tilted_jet_does_not_grow_faster_than_the_plume_allows():
    """A 0.75 mm spike 10 mm tall sprayed by a jet tilted 35 degrees for 3 s: its top may rise
    at most by the plume's peak rate (packets that would land on its 0.56 mm^2 top), not by
    the packets its sides intercept; the rest of what sticks lands around its foot."""
    p = ProcessConfig(feed_g_min=26.0)
    hf, (lo, hi) = _spike_field(3, 10.0)
    before = hf.heights_mm.copy()
    model = SprayModel(p, seed=7)
    tilt = math.radians(35.0)
    axis = np.array([math.sin(tilt), 0.0, -math.cos(tilt)])
    spot = np.array([20.0, 20.0, 10.0])
    model.deposit(hf, spot, axis, dt_s=3.0)
    after = hf.heights_mm
    sigma = plume_sigma_mm(p)
    # the plume's peak areal rate on a flat face normal to the jet [mm/s]
    peak_mm_s = volume_rate_mm3_s(p) * p.deposition_efficiency / (2 * math.pi * sigma ** 2)
    top_rise = float(after[lo:hi, lo:hi].max() - 10.0)
    assert top_rise <= peak_mm_s * 3.0
    # volume: what the field gained is what the model says stuck
    gained = float((after - before).sum()) * CELL * CELL
    assert math.isclose(gained, model.deposited_volume_mm3, rel_tol=1e-9)
    # most of it lies off the spike's own cells, on the plate around it
    on_spike = float((after - before)[lo - 2:hi + 2, lo - 2:hi + 2].sum()) * CELL * CELL
    assert on_spike < 0.1 * gained


def test_impact_normal_reads_a_narrow_spike_as_steep_and_a_narrow_pit_as_flat():
    """One node 2 mm above a flat field reads as a 53 deg crest (its flanks over the 1.5 mm
    stencil), where a central difference reads it flat; one node 2 mm below reads flat, so
    a pit fills instead of losing efficiency and deepening."""
    k = 6
    spike = np.zeros((41, 41))
    spike[20, 20] = 2.0
    gx, gy = DK._robust_gradient(spike, CELL, 20.1 * CELL, 20.1 * CELL, k)
    assert math.isclose(abs(gx), 2.0 / (k * CELL)) and math.isclose(abs(gy), 2.0 / (k * CELL))
    gx, gy = DK._robust_gradient(-spike, CELL, 20.1 * CELL, 20.1 * CELL, k)
    assert gx == 0.0 and gy == 0.0
