"""Tall builds keep their nominal growth: the impact angle is taken against the macroscopic
surface, so the packets' own shot noise neither costs efficiency nor roughens the part."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

from dm2.core.config import ProcessConfig
from twin.world.deposition import SprayModel, deposition_efficiency, volume_rate_mm3_s
from twin.world.heightfield import HeightField

DT = 1.0 / 250.0
DOWN = np.array([0.0, 0.0, -1.0])


def _raster(lo, hi, spacing, speed, z, vertical, reverse):
    lines = np.arange(lo, hi + 1e-9, spacing)[::-1 if reverse else 1]
    pts = np.array([p for k, c in enumerate(lines)
                    for p in (((lo, c), (hi, c)) if k % 2 == 0 else ((hi, c), (lo, c)))])
    if vertical:
        pts = pts[:, ::-1]
    s = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))]
    q = np.arange(0.0, s[-1], speed * DT)
    return np.column_stack([np.interp(q, s, pts[:, 0]), np.interp(q, s, pts[:, 1]),
                            np.full(q.size, z)])


def _rough_plane(slope_deg: float, rms_mm: float, seed: int) -> HeightField:
    """A plane rising along x at ``slope_deg`` plus seeded roughness (correlation ~0.5 mm)."""
    hf = HeightField((40.0, 40.0), 0.25, 6.0)
    x, _ = hf.centres_mm()
    noise = gaussian_filter(np.random.default_rng(seed).normal(size=hf.shape), 2.0)
    noise *= rms_mm / noise.std()
    hf.heights_mm = 5.0 + math.tan(math.radians(slope_deg)) * (x[None, :] - 20.0) + noise
    return hf


@pytest.mark.parametrize("slope_deg", [0.0, 30.0, 50.0])
def test_rough_surface_deposits_with_the_efficiency_of_its_mean_slope(slope_deg):
    # 0.2 mm rms roughness on the packets' scale: about what the twin's own shot noise
    # leaves after ten passes; a vertical jet must stick with zeta(mean slope)
    p = ProcessConfig(feed_g_min=26.0)
    hf = _rough_plane(slope_deg, 0.2, seed=5)
    model = SprayModel(p, seed=3)
    n = 250
    vol = model.deposit_samples(hf, np.tile([20.0, 20.0, 5.0], (n, 1)), np.tile(DOWN, (n, 1)),
                                DT)
    assert model.missed_packets == 0
    expected = deposition_efficiency(p, math.radians(slope_deg))
    assert vol.sum() / model.fed_volume_mm3 == pytest.approx(expected, rel=0.02)


@pytest.mark.slow  # 30 passes of a 32 x 32 mm raster: about 9 minutes of process
def test_flat_raster_grows_its_nominal_layer_for_thirty_passes():
    # 26 g/min of CP-Ti at 30 mm/s and 2 mm spacing, 50 % efficiency: 0.80 mm per pass
    p = ProcessConfig(feed_g_min=26.0)
    nominal = volume_rate_mm3_s(p) * p.deposition_efficiency / (30.0 * 2.0)
    assert nominal == pytest.approx(0.80, abs=0.005)
    hf = HeightField((60.0, 60.0), 0.25, 6.0)
    model = SprayModel(p, seed=7)
    window = (slice(110, 130), slice(110, 130))  # the central 5 x 5 mm, clear of the edge taper
    n_pass = 30
    for k in range(n_pass):  # crosshatch, forward and reverse passes like the double strategy
        spots = _raster(14.0, 46.0, 2.0, 30.0, nominal * (k + 1), (k // 2) % 2 == 1, k % 2 == 1)
        model.deposit_samples(hf, spots, np.tile(DOWN, (len(spots), 1)), DT)
    centre = hf.heights_mm[window]
    assert centre.mean() == pytest.approx(n_pass * nominal, rel=0.02)
    # as smooth as a fine powder's deposit (evenly placed packets), and not running away
    assert centre.std() < 0.12
