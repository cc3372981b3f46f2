"""SprayModel: mass conservation, Gaussian footprint, angle-dependent efficiency, determinism."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.optimize import curve_fit

from dm2.core.config import ProcessConfig
from twin.world.deposition import (
    SprayModel,
    deposition_efficiency,
    plume_sigma_mm,
    volume_rate_mm3_s,
)
from twin.world.heightfield import HeightField

DT = 1.0 / 250.0


def raster_samples(x0, x1, y0, y1, spacing, speed, z, dt=DT, vertical_first=False):
    """Serpentine raster over a rectangle sampled at constant speed: (m, 3) spots."""
    ys = np.arange(y0, y1 + 1e-9, spacing)
    pts = []
    for k, y in enumerate(ys):
        xa, xb = (x0, x1) if k % 2 == 0 else (x1, x0)
        pts += [(xa, y), (xb, y)]
    pts = np.array(pts)
    if vertical_first:
        pts = pts[:, ::-1]
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    s = np.concatenate([[0], np.cumsum(seg)])
    q = np.arange(0, s[-1], speed * dt)
    xy = np.column_stack([np.interp(q, s, pts[:, 0]), np.interp(q, s, pts[:, 1])])
    return np.column_stack([xy, np.full(len(q), z)])


def test_mass_conservation_per_layer():
    p = ProcessConfig()
    hf = HeightField((40.0, 40.0), 0.25, 6.0)
    model = SprayModel(p, seed=11)
    down = np.array([0.0, 0.0, -1.0])
    for layer in range(2):
        spots = raster_samples(12, 28, 12, 28, 2.0, 30.0, 0.8 * layer, vertical_first=layer % 2)
        v0 = hf.heights_mm.sum() * hf.cell_mm**2
        vol = model.deposit_samples(hf, spots, np.tile(down, (len(spots), 1)), DT)
        gained = hf.heights_mm.sum() * hf.cell_mm**2 - v0
        nominal = volume_rate_mm3_s(p) * len(spots) * DT * p.deposition_efficiency
        assert gained == pytest.approx(vol.sum(), rel=1e-9)  # the grid keeps what was added
        assert gained == pytest.approx(nominal, rel=0.01)
    assert model.missed_packets < 1e-4 * model.fed_volume_mm3 / model.v_packet_mm3
    assert model.deposited_volume_mm3 == pytest.approx(
        model.fed_volume_mm3 * p.deposition_efficiency, rel=0.01)


def _gauss2d(xy, a, x0, y0, s):
    return a * np.exp(-((xy[0] - x0) ** 2 + (xy[1] - y0) ** 2) / (2 * s * s))


def test_static_spot_is_gaussian_with_configured_sigma_and_peak():
    p = ProcessConfig()
    hf = HeightField((40.0, 40.0), 0.25, 6.0)
    model = SprayModel(p, seed=5)
    t_s = 1.0
    n = int(round(t_s / DT))
    model.deposit_samples(hf, np.tile([20.0, 20.0, 0.0], (n, 1)),
                          np.tile([0.0, 0.0, -1.0], (n, 1)), DT)
    x, y = hf.centres_mm()
    gx, gy = np.meshgrid(x, y)
    (a, x0, y0, s), _ = curve_fit(_gauss2d, (gx.ravel(), gy.ravel()), hf.heights_mm.ravel(),
                                  p0=(0.1, 19.0, 21.0, 2.0))
    sigma = plume_sigma_mm(p)
    peak = volume_rate_mm3_s(p) * t_s * p.deposition_efficiency / (2 * math.pi * sigma**2)
    assert sigma == pytest.approx(2.95, abs=0.01)
    assert abs(s) == pytest.approx(sigma, rel=0.05)
    assert a == pytest.approx(peak, rel=0.05)
    assert abs(x0 - 20.0) < 0.1 and abs(y0 - 20.0) < 0.1


def test_packets_sample_the_plume_evenly_as_fine_powder_would():
    # one second of a static spot: 5,000 packets of a few hundred particles each. A real jet of
    # millions of particles paints the plume's profile smoothly; packets placed independently
    # would leave shot noise of about 4 % of the peak rms (14 % at worst), evenly placed
    # packets must leave under 1 %. The expected profile is the plume's Gaussian widened by
    # the one-cell splat.
    p = ProcessConfig()
    hf = HeightField((40.0, 40.0), 0.25, 6.0)
    model = SprayModel(p, seed=5)
    n = 250
    model.deposit_samples(hf, np.tile([20.0, 20.0, 0.0], (n, 1)),
                          np.tile([0.0, 0.0, -1.0], (n, 1)), DT)
    x, y = hf.centres_mm()
    gx, gy = np.meshgrid(x, y)
    var = plume_sigma_mm(p) ** 2 + hf.cell_mm ** 2
    peak = volume_rate_mm3_s(p) * n * DT * p.deposition_efficiency / (2 * math.pi * var)
    r2 = (gx - 20.0) ** 2 + (gy - 20.0) ** 2
    inside = r2 < (2.5 ** 2) * var
    residual = (hf.heights_mm - peak * np.exp(-r2 / (2 * var)))[inside] / peak
    assert np.sqrt(np.mean(residual ** 2)) < 0.008
    assert np.abs(residual).max() < 0.03


def test_standoff_and_configured_sigma_scale_the_plume():
    p = ProcessConfig()
    assert plume_sigma_mm(p, 10.0) > plume_sigma_mm(p) > plume_sigma_mm(p, -10.0)
    q = ProcessConfig(plume_sigma_mm=4.0)
    assert plume_sigma_mm(q) == pytest.approx(4.0)
    assert plume_sigma_mm(q, 10.0) / 4.0 == pytest.approx(plume_sigma_mm(p, 10.0)
                                                          / plume_sigma_mm(p))


def test_efficiency_curve_shape():
    p = ProcessConfig(deposition_efficiency=0.6, critical_angle_deg=75.0)
    th = np.radians([0.0, 15.0, 60.0, 74.9, 75.0, 85.0])
    z = deposition_efficiency(p, th)
    assert z[0] == pytest.approx(0.6)
    assert 0.97 * 0.6 < z[1] < 0.6
    assert z[2] == pytest.approx(0.6 * math.cos(0.5 * math.pi * 0.64) ** 2)
    assert 0 < z[3] < 1e-4 and z[4] == 0 and z[5] == 0
    assert np.all(np.diff(z) <= 0)


def test_tilted_60_degree_spray_deposits_zeta_60():
    p = ProcessConfig()
    hf = HeightField((60.0, 60.0), 0.25, 6.0)
    model = SprayModel(p, seed=2)
    a = math.radians(60.0)
    axis = np.array([math.sin(a), 0.0, -math.cos(a)])
    n = 125  # 0.5 s static
    vol = model.deposit_samples(hf, np.tile([30.0, 30.0, 0.0], (n, 1)), np.tile(axis, (n, 1)),
                                DT)
    expected = deposition_efficiency(p, a)
    assert model.missed_packets == 0
    assert vol.sum() / model.fed_volume_mm3 == pytest.approx(expected, rel=0.02)
    # the footprint is stretched by 1 / cos(60 deg) along the tilt direction
    h = hf.heights_mm
    x, y = hf.centres_mm()
    wx = np.sqrt(np.sum(h.sum(0) * (x - np.average(x, weights=h.sum(0))) ** 2) / h.sum())
    wy = np.sqrt(np.sum(h.sum(1) * (y - np.average(y, weights=h.sum(1))) ** 2) / h.sum())
    assert wx / wy == pytest.approx(2.0, rel=0.08)


def test_same_seed_same_deposit_bit_for_bit():
    p = ProcessConfig()
    spots = raster_samples(10, 20, 10, 20, 2.0, 30.0, 0.0)
    tilt = np.tile([0.3, 0.0, -math.sqrt(1 - 0.09)], (len(spots), 1))
    results = []
    for seed in (4, 4, 5):
        hf = HeightField((30.0, 30.0), 0.25, 6.0)
        m = SprayModel(p, seed=seed)
        m.deposit_samples(hf, spots, tilt, DT)
        for k in range(20):  # the single-step API draws from the same stream
            m.deposit(hf, spots[k], tilt[k], DT)
        results.append(hf.heights_mm.copy())
    assert np.array_equal(results[0], results[1])
    assert not np.array_equal(results[0], results[2])


def test_feed_factor_and_residence_time_scale_the_deposit():
    p = ProcessConfig()
    vols = []
    for ff, dt in ((1.0, DT), (0.5, DT), (1.0, 2 * DT)):
        hf = HeightField((30.0, 30.0), 0.25, 6.0)
        m = SprayModel(p, seed=9)
        vols.append(m.deposit_samples(hf, np.tile([15.0, 15.0, 0.0], (500, 1)),
                                      np.tile([0.0, 0.0, -1.0], (500, 1)), dt,
                                      feed_factor=ff).sum())
    assert vols[1] / vols[0] == pytest.approx(0.5, rel=0.03)
    assert vols[2] / vols[0] == pytest.approx(2.0, rel=0.03)
    with pytest.raises(ValueError, match="non-negative"):
        SprayModel(p).deposit(HeightField((10.0, 10.0), 0.5), [5, 5, 0], [0, 0, -1], -1.0)


def test_unrolled_splat_equals_general_path_bit_for_bit():
    from twin.world import splat_kernels as SK

    rng = np.random.default_rng(4)
    h0 = rng.uniform(0.0, 0.3, (32, 40))
    xy = rng.uniform([0.6, 0.6], [9.4, 7.4], (400, 2))  # every splat's 5 x 5 cells on the grid
    vols = rng.uniform(1e-4, 1e-2, 400)
    w = np.empty(2 * (2 * SK.SPLAT_RADIUS_CELLS + 1))
    grown = []
    for unrolled in (True, False):
        hf = HeightField((10.0, 8.0), 0.25, 6.0)
        hf.heights_mm = h0
        for (x, y), vol in zip(xy, vols, strict=True):
            SK.splat(hf._h, hf._bmax, hf._zmax, hf._dirty, hf.cell_mm, x, y, vol, w, unrolled)
        grown.append(hf)
    for name in ("_h", "_bmax", "_zmax", "_dirty"):
        np.testing.assert_array_equal(getattr(grown[0], name), getattr(grown[1], name),
                                      err_msg=name)
    added_mm3 = (grown[0]._h - h0).sum() * 0.25 ** 2
    assert math.isclose(added_mm3, vols.sum(), rel_tol=1e-9)
