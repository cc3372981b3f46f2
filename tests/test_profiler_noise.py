"""Virtual profiler noise: statistics against the configured sigmas, determinism by seed."""

from __future__ import annotations

import numpy as np

from dm2.core.config import SensorConfig
from dm2.core.frames import from_euler_deg, look_at
from twin.profiler.model import DROPOUT, VALID
from twin.profiler.sensor import VirtualProfiler
from twin.schema import NoiseConfig
from twin.world.heightfield import HeightField

SENSORS = SensorConfig()
T_B_O = from_euler_deg([1300.0, 20.0, 780.0], [-20.0, 0.0, 2.0])
N_PROFILES = 16  # 16 x 640 = 10,240 samples


def _setup(noise: NoiseConfig, seed: int = 5, sensor_id: str = "S2"):
    hf = HeightField((120.0, 120.0), 0.25, 6.0)
    target = np.array([60.0, 60.0, 0.0])
    el, az = np.radians(55.0), np.radians(210.0)
    origin = target + 95.0 * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az),
                                       np.sin(el)])
    prof = VirtualProfiler(sensor_id, T_B_O @ look_at(origin, target), SENSORS, noise, seed)
    return hf, prof


def _range_errors(noise: NoiseConfig):
    """Measured minus true range for all points of N_PROFILES profiles, and validity."""
    hf, prof = _setup(noise)
    trace = prof.trace(hf, T_B_O)
    assert np.all(trace.reason == VALID)
    errs, valid = [], []
    for counter in range(N_PROFILES):
        p = prof.scan(hf, T_B_O, 0.1 * counter, counter)
        errs.append(np.linalg.norm(p.xz_S, axis=1) - trace.range_mm)
        valid.append(p.valid)
    return np.array(errs), np.array(valid)


def test_range_noise_matches_sigma_and_is_white():
    sigma = 0.04
    err, valid = _range_errors(NoiseConfig(range_sigma_mm=sigma, min_intensity=0.0))
    assert valid.all() and err.size >= 10_000
    assert abs(err.std() / sigma - 1.0) < 0.1
    assert abs(err.mean()) < 4 * sigma / np.sqrt(err.size)
    lag1 = np.mean([np.corrcoef(e[:-1], e[1:])[0, 1] for e in err])
    assert abs(lag1) < 0.05


def test_speckle_matches_sigma_and_is_correlated_along_the_line():
    sigma = 0.03
    err, valid = _range_errors(NoiseConfig(range_sigma_mm=0.0, speckle_sigma_mm=sigma,
                                           speckle_length_points=4.0, min_intensity=0.0))
    assert valid.all()
    assert abs(err.std() / sigma - 1.0) < 0.1
    lag1 = np.mean([np.corrcoef(e[:-1], e[1:])[0, 1] for e in err])
    assert lag1 > 0.9  # Gaussian kernel of 4 points: exp(-1 / 64) = 0.98


def test_dropouts_and_multiple_reflection_ghosts_at_their_rates():
    p_drop, p_ghost, lo, hi = 0.2, 0.1, 0.5, 5.0
    err, valid = _range_errors(NoiseConfig(range_sigma_mm=0.0, dropout_prob=p_drop,
                                           outlier_prob=p_ghost, outlier_offset_mm=(lo, hi),
                                           min_intensity=0.0))
    assert abs((~valid).mean() / p_drop - 1.0) < 0.1
    e = err[valid]
    assert np.all(np.isnan(err[~valid]))
    ghosts = e > 1e-9
    np.testing.assert_allclose(e[~ghosts], 0.0, atol=1e-9)  # the rest is exact
    assert abs(ghosts.mean() / p_ghost - 1.0) < 0.1
    assert e[ghosts].min() >= lo and e[ghosts].max() <= hi  # beyond the surface, along the ray
    assert abs(e[ghosts].mean() / ((lo + hi) / 2) - 1.0) < 0.1


def test_invalid_points_are_marked_like_the_sensor_does():
    hf, prof = _setup(NoiseConfig(dropout_prob=0.3))
    trace = prof.trace(hf, T_B_O)
    p = prof.scan(hf, T_B_O, 0.0, 9)
    assert 0 < p.valid.sum() < p.n_points
    assert np.all(np.isnan(p.xz_S[~p.valid])) and np.all(np.isfinite(p.xz_S[p.valid]))
    assert np.all(p.intensity[~p.valid] == 0)
    noisy_reason = prof._noise(trace, 9)[1]
    np.testing.assert_array_equal(noisy_reason == DROPOUT, ~p.valid)


def _same(a, b):
    return (np.array_equal(a.xz_S, b.xz_S, equal_nan=True) and np.array_equal(a.valid, b.valid)
            and np.array_equal(a.intensity, b.intensity))


def test_same_seed_gives_identical_profiles_in_any_order():
    noise = NoiseConfig(range_sigma_mm=0.05, speckle_sigma_mm=0.02, dropout_prob=0.05,
                        outlier_prob=0.02)
    hf, a = _setup(noise, seed=42)
    _, b = _setup(noise, seed=42)
    forward = [a.scan(hf, T_B_O, 0.1 * c, c) for c in range(4)]
    backward = [b.scan(hf, T_B_O, 0.1 * c, c) for c in reversed(range(4))][::-1]
    assert all(_same(x, y) for x, y in zip(forward, backward, strict=True))
    assert not _same(forward[0], forward[1])  # each counter draws its own noise
    _, other_seed = _setup(noise, seed=43)
    assert not _same(forward[0], other_seed.scan(hf, T_B_O, 0.0, 0))
    _, other_sensor = _setup(noise, seed=42, sensor_id="S3")
    assert not _same(forward[0], other_sensor.scan(hf, T_B_O, 0.0, 0))
