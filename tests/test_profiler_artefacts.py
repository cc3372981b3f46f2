"""The profilers' cold-spray artefacts (twin.profiler.artefacts): each found where and as large
as it was put, nothing else changed, seeded; off by default."""

from __future__ import annotations

import numpy as np
import pytest

from dm2.core.config import PointFilterConfig, SensorConfig
from dm2.core.frames import from_euler_deg, look_at
from dm2.fusion.point_filter import KEEP, line_outliers
from twin.profiler.artefacts import DRIFT_SHARE, schedule_artefacts
from twin.profiler.sensor import VirtualProfiler
from twin.schema import NOISE_PRESETS, NoiseConfig
from twin.world.heightfield import HeightField

SENSORS = SensorConfig()
T_B_O = from_euler_deg([1300.0, 20.0, 780.0], [-20.0, 0.0, 2.0])
TARGET_O = np.array([60.0, 60.0, 0.0])


def _profiler(noise: NoiseConfig, seed: int = 5, T_B_N=None):
    hf = HeightField((120.0, 120.0), 0.25, 6.0)
    el, az = np.radians(55.0), np.radians(210.0)
    origin = TARGET_O + 95.0 * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az),
                                         np.sin(el)])
    return hf, VirtualProfiler("S2", T_B_O @ look_at(origin, TARGET_O), SENSORS, noise, seed,
                               T_B_N=T_B_N)


def _clean_and_dirty(**artefacts):
    """A profile of a flat plate without noise, and the same with ``artefacts`` on."""
    hf, clean = _profiler(NoiseConfig(range_sigma_mm=0.0))
    _, dirty = _profiler(NoiseConfig(range_sigma_mm=0.0, **artefacts))
    return (clean.scan(hf, T_B_O, 1.0, 7), dirty.scan(hf, T_B_O, 1.0, 7), dirty,
            hf)


def _ranges(p):
    return np.linalg.norm(p.xz_S, axis=1)


def test_defaults_are_clean_and_give_the_same_bits():
    assert not NoiseConfig().dirty()
    hf, a = _profiler(NoiseConfig())
    _, b = _profiler(NoiseConfig(), T_B_N=np.eye(4))
    pa, pb = a.scan(hf, T_B_O, 2.0, 3), b.scan(hf, T_B_O, 2.0, 3)
    np.testing.assert_array_equal(pa.xz_S, pb.xz_S)
    np.testing.assert_array_equal(pa.intensity, pb.intensity)


@pytest.mark.parametrize("counter", [1, 2, 3, 4])
def test_burst_is_one_stretch_at_one_offset(counter):
    hf, clean = _profiler(NoiseConfig(range_sigma_mm=0.0))
    _, prof = _profiler(NoiseConfig(range_sigma_mm=0.0, burst_prob=1.0))
    c, d = clean.scan(hf, T_B_O, 1.0, counter), prof.scan(hf, T_B_O, 1.0, counter)
    both = c.valid & d.valid
    diff = np.where(both, _ranges(d) - _ranges(c), 0.0)
    moved = np.flatnonzero(np.abs(diff) > 1e-9)
    assert 3 <= moved.size <= 12 and np.all(np.diff(moved) == 1)
    off = diff[moved]
    assert np.allclose(off, off[0]) and 0.4 <= abs(off[0]) <= 3.0
    np.testing.assert_array_equal(d.valid, c.valid)  # a flat plate: nothing leaves the range


def test_ghost_line_lies_behind_growing_along_the_stretch():
    c, d, _, _ = _clean_and_dirty(ghost_line_prob=1.0)
    diff = np.where(c.valid & d.valid, _ranges(d) - _ranges(c), 0.0)
    moved = np.flatnonzero(np.abs(diff) > 1e-9)
    assert 4 <= moved.size <= 12 and np.all(np.diff(moved) == 1)
    assert np.all(diff[moved] >= 0.4) and np.all(np.diff(diff[moved]) > 0)
    np.testing.assert_allclose(d.intensity[moved], 0.5 * c.intensity[moved], rtol=1e-6)


@pytest.mark.parametrize("counter", range(6))
def test_specular_run_is_lost_or_saturated(counter):
    hf, clean = _profiler(NoiseConfig(range_sigma_mm=0.0))
    _, prof = _profiler(NoiseConfig(range_sigma_mm=0.0, specular_run_prob=1.0))
    c, d = clean.scan(hf, T_B_O, 1.0, counter), prof.scan(hf, T_B_O, 1.0, counter)
    lost = np.flatnonzero(c.valid & ~d.valid)
    both = c.valid & d.valid
    biased = np.flatnonzero(both & (np.abs(np.where(both, _ranges(d) - _ranges(c), 0)) > 1e-9))
    assert (lost.size == 0) != (biased.size == 0)
    run = lost if lost.size else biased
    assert np.all(np.diff(run) == 1) and run.size <= 40
    if biased.size:
        np.testing.assert_allclose(_ranges(d)[biased] - _ranges(c)[biased], 0.05, atol=1e-9)
        assert np.all(d.intensity[biased] == 1.0)


def test_mount_drift_grows_with_process_time_per_sensor_share():
    hf, clean = _profiler(NoiseConfig(range_sigma_mm=0.0))
    _, prof = _profiler(NoiseConfig(range_sigma_mm=0.0, mount_drift_mm_min=0.02))
    for stamp in (0.0, 60.0, 300.0):
        c, d = clean.scan(hf, T_B_O, stamp, 1), prof.scan(hf, T_B_O, stamp, 1)
        v = c.valid & d.valid
        dz = d.xz_S[v, 1] - c.xz_S[v, 1]
        np.testing.assert_allclose(dz, 0.02 * DRIFT_SHARE[1] * stamp / 60.0, atol=1e-9)
        np.testing.assert_allclose(d.xz_S[v, 0], c.xz_S[v, 0], atol=1e-12)


def test_plume_particles_lie_in_front_near_the_jet_and_only_while_spraying():
    # a jet straight down onto the plate's centre, where the fan looks
    T_B_N = np.eye(4)
    T_B_N[:3, :3] = np.diag([1.0, -1.0, -1.0])  # +z_N points down
    T_B_N[:3, 3] = (T_B_O @ np.append(TARGET_O + [0.0, 0.0, 30.0], 1.0))[:3]
    T_B_N[:3, :3] = T_B_O[:3, :3] @ T_B_N[:3, :3]
    noise = NoiseConfig(range_sigma_mm=0.0, plume_particle_prob=0.5)
    hf, clean = _profiler(NoiseConfig(range_sigma_mm=0.0))
    _, prof = _profiler(noise, T_B_N=T_B_N)
    n_front = 0
    for counter in range(10):
        c = clean.scan(hf, T_B_O, 1.0, counter)
        off = prof.scan(hf, T_B_O, 1.0, counter, spray=0.0)
        np.testing.assert_array_equal(off.xz_S, c.xz_S)
        d = prof.scan(hf, T_B_O, 1.0, counter, spray=1.0)
        moved = c.valid & d.valid & (np.abs(_ranges(d) - _ranges(c)) > 1e-9)
        assert np.all(_ranges(d)[moved] < _ranges(c)[moved] - 0.3)  # in front
        n_front += int(moved.sum())
    assert n_front > 10


def test_schedule_jitter_and_lost_profiles():
    stamps = np.arange(0.0, 200.0, 0.01)
    noise = NoiseConfig(clock_jitter_ms=1.0, lost_profile_prob=0.005)
    out, kept = schedule_artefacts(noise, 3, stamps)
    assert np.abs(out - stamps).max() <= 1e-3 and np.abs(out - stamps).max() > 0.9e-3
    assert 0.004 < 1.0 - kept.mean() < 0.006
    out2, kept2 = schedule_artefacts(noise, 3, stamps)  # seeded
    np.testing.assert_array_equal(out, out2)
    np.testing.assert_array_equal(kept, kept2)
    same, all_kept = schedule_artefacts(NoiseConfig(), 3, stamps)
    assert same is stamps or np.array_equal(same, stamps)
    assert all_kept.all()


def test_realistic_preset_and_overrides():
    cfg = NoiseConfig(preset="realistic", burst_prob=0.0)
    for key, value in NOISE_PRESETS["realistic"].items():
        assert getattr(cfg, key) == (0.0 if key == "burst_prob" else value)
    assert cfg.dirty()
    with pytest.raises(ValueError, match="burst_points"):
        NoiseConfig(burst_points=(5, 2))


@pytest.mark.parametrize("counter", range(8))
def test_filter_takes_out_exactly_a_twin_burst(counter):
    # the pipeline's point filter on the twin's profile: the burst's rays, nothing else
    noise = NoiseConfig(range_sigma_mm=0.05, burst_prob=1.0, burst_offset_mm=(1.0, 3.0))
    hf, prof = _profiler(noise)
    _, clean = _profiler(NoiseConfig(range_sigma_mm=0.05))
    d, c = prof.scan(hf, T_B_O, 1.0, counter), clean.scan(hf, T_B_O, 1.0, counter)
    burst = np.flatnonzero(d.valid & (np.abs(_ranges(d) - _ranges(c)) > 0.5))
    xz = np.ascontiguousarray(d.xz_S[d.valid])
    reason = np.empty(len(xz), np.int8)
    cfg = PointFilterConfig()
    line_outliers(xz, np.array([0, len(xz)]), cfg.reject_mm, cfg.agree_mm, cfg.max_step_mm,
                  cfg.max_run_points, reason)
    rays = np.flatnonzero(d.valid)
    np.testing.assert_array_equal(rays[reason != KEEP], burst)


def test_filter_kernel_equals_its_plain_statement_on_dirty_twin_profiles():
    from tests.oracles.point_filter_numpy import line_outliers_numpy

    noise = NoiseConfig(preset="realistic", burst_prob=0.5, ghost_line_prob=0.5,
                        outlier_prob=0.01)
    hf, prof = _profiler(noise)
    cfg = PointFilterConfig()
    xzs = [np.ascontiguousarray(p.xz_S[p.valid]) for p in
           (prof.scan(hf, T_B_O, 0.1 * k, k) for k in range(40))]
    xz = np.concatenate(xzs)
    offsets = np.concatenate([[0], np.cumsum([len(a) for a in xzs])])
    got = np.empty(len(xz), np.int8)
    line_outliers(xz, offsets, cfg.reject_mm, cfg.agree_mm, cfg.max_step_mm,
                  cfg.max_run_points, got)
    want = line_outliers_numpy(xz, offsets, cfg.reject_mm, cfg.agree_mm, cfg.max_step_mm,
                               cfg.max_run_points)
    assert (want != KEEP).sum() > 100  # the artefacts were found
    np.testing.assert_array_equal(got, want)
