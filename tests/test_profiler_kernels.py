"""The profiler's numba scan (trace, noise, and both in one call) gives the same bits as its
numpy path: on a rough deposit, at the plate's edge, behind an occluder and in the dark,
with every noise term switched on."""

from __future__ import annotations

import numpy as np
import pytest

from dm2.core.config import SensorConfig
from dm2.core.frames import from_euler_deg, make_T
from twin.profiler.model import (
    BACK_FACING,
    CAMERA_BLOCKED,
    CAMERA_SHADOW,
    LASER_BLOCKED,
    NO_SURFACE,
    TOO_DARK,
    VALID,
)
from twin.profiler.occluders import CylinderOccluder
from twin.profiler.sensor import VirtualProfiler
from twin.schema import NoiseConfig
from twin.world.heightfield import HeightField

T_B_O = from_euler_deg([1250.0, -40.0, 820.0], [30.0, 4.0, -3.0])
NOISY = NoiseConfig(range_sigma_mm=0.03, speckle_sigma_mm=0.02, dropout_prob=0.05,
                    outlier_prob=0.05, min_intensity=0.3)


def _rough_field() -> HeightField:
    """Steep random ridges (rough, with walls that shadow and face away) on a 40 mm plate."""
    rng = np.random.default_rng(11)
    hf = HeightField((40.0, 40.0), 0.25, 6.0)
    x, y = hf.centres_mm()
    gx, gy = np.meshgrid(x, y)
    h = np.zeros_like(gx)
    for _ in range(25):
        cx, cy, w = rng.uniform(5, 35), rng.uniform(5, 35), rng.uniform(0.4, 2.5)
        h += rng.uniform(1.0, 4.0) * np.exp(-((gx - cx) ** 2 + (gy - cy) ** 2) / (2 * w * w))
    hf.heights_mm = h
    return hf


def _T_O_S(target, elevation_deg, azimuth_deg, flip=False, distance_mm=95.0):
    """Profiler pose in O aimed at ``target``; ``flip`` turns it about +z_S (camera below)."""
    el, az = np.radians(elevation_deg), np.radians(azimuth_deg)
    toward = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), -np.sin(el)])
    x = np.cross([0.0, 0.0, 1.0], toward)
    x /= np.linalg.norm(x)
    T = make_T(np.column_stack([x, np.cross(toward, x), toward]),
               np.asarray(target, float) - distance_mm * toward)
    return T @ np.diag([-1.0, -1.0, 1.0, 1.0]) if flip else T


def _rods(T_B_S, sensors: SensorConfig):
    """A rod across part of the laser fan and one across the camera's view, both along x_S."""
    along_x = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])  # z_C = x_S
    laser = make_T(along_x, [6.0, 0.0, 50.0]) @ make_T(np.eye(3), [0.0, 0.0, -3.0])
    b = sensors.camera_baseline_mm
    camera = make_T(along_x, [-8.0, 0.45 * b, 45.0]) @ make_T(np.eye(3), [0.0, 0.0, -3.0])
    return (CylinderOccluder(T_B_S @ laser, 1.5, 6.0, "laser rod"),
            CylinderOccluder(T_B_S @ camera, 2.0, 6.0, "camera rod"))


CASES = [((20.0, 20.0, 1.0), 55.0, 0.0, False),   # rough deposit
         ((20.0, 20.0, 1.0), 20.0, 140.0, True),  # grazing: shadows, back faces, dark points
         ((20.0, 20.0, 1.0), 35.0, 0.0, True),
         ((1.0, 20.0, -2.0), 40.0, 180.0, False)]  # across the plate's edge: side faces


@pytest.mark.parametrize("target, elevation, azimuth, flip", CASES)
def test_numba_scan_equals_numpy_reference(target, elevation, azimuth, flip):
    hf = _rough_field()
    sensors = SensorConfig()
    T_B_S = T_B_O @ _T_O_S(target, elevation, azimuth, flip)
    prof = VirtualProfiler("S2", T_B_S, sensors, NOISY, seed=5)
    seen = set()
    for occluders in ((), _rods(T_B_S, sensors)):
        fast = prof.trace(hf, T_B_O, occluders)
        ref = prof.trace_numpy(hf, T_B_O, occluders)
        for name in ("range_mm", "reason", "cos_incidence", "points_O"):
            np.testing.assert_array_equal(getattr(fast, name), getattr(ref, name), err_msg=name)
        seen |= set(np.unique(fast.reason).tolist())
        parts = prof.empty_trace()  # the fan cast in three parts, as two threads share it
        for r0, r1 in ((217, 640), (0, 5), (5, 217)):
            prof.trace_rays(hf, T_B_O, occluders, parts, r0, r1)
        for name in ("range_mm", "reason", "cos_incidence", "points_O"):
            np.testing.assert_array_equal(getattr(parts, name), getattr(fast, name),
                                          err_msg=name)
        for counter in (0, 77):
            a = prof.measure(fast, 1.5, counter)
            b = prof.measure_numpy(ref, 1.5, counter)
            for name in ("xz_S", "valid", "intensity"):
                np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
            assert a.intensity.dtype == np.float32 and 0 < a.valid.sum() < a.n_points
            whole = prof.scan(hf, T_B_O, 1.5, counter, occluders)  # one kernel call
            for name in ("xz_S", "valid", "intensity"):
                np.testing.assert_array_equal(getattr(whole, name), getattr(b, name),
                                              err_msg=name)
    assert VALID in seen and len(seen) >= 3


def test_cases_cover_every_geometric_reason():
    hf = _rough_field()
    sensors = SensorConfig()
    reasons = set()
    for target, el, az, flip in CASES:
        T_B_S = T_B_O @ _T_O_S(target, el, az, flip)
        prof = VirtualProfiler("S2", T_B_S, sensors, NOISY, seed=5)
        reasons |= set(np.unique(prof.trace(hf, T_B_O, _rods(T_B_S, sensors)).reason).tolist())
    assert reasons == {VALID, NO_SURFACE, LASER_BLOCKED, CAMERA_SHADOW, CAMERA_BLOCKED,
                       BACK_FACING, TOO_DARK}
