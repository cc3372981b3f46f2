"""Virtual profiler geometry: flat plate, step shadows, occluders, measuring range."""

from __future__ import annotations

import numpy as np
import pytest

from dm2.core.config import SensorConfig
from dm2.core.frames import apply, from_euler_deg, invert, make_T
from twin.profiler.model import (
    CAMERA_BLOCKED,
    CAMERA_SHADOW,
    LASER_BLOCKED,
    NO_SURFACE,
    TOO_DARK,
    VALID,
)
from twin.profiler.occluders import CylinderOccluder, nozzle_occluder
from twin.profiler.sensor import VirtualProfiler
from twin.schema import CellConfig, NoiseConfig
from twin.world.heightfield import HeightField

SENSORS = SensorConfig()
QUIET = NoiseConfig(range_sigma_mm=0.0, min_intensity=0.0)
T_B_O = from_euler_deg([1250.0, -40.0, 820.0], [30.0, 4.0, -3.0])  # plate pose in B


def sensor_T_O_S(target_O, distance_mm=95.0, elevation_deg=55.0, azimuth_deg=0.0,
                 camera_behind=False):
    """Profiler pose in O: ``distance_mm`` from ``target_O``, +z_S aimed at it, x_S horizontal.

    The camera offset +y_S points towards the target and up, or away and down when
    ``camera_behind``.
    """
    el, az = np.radians(elevation_deg), np.radians(azimuth_deg)
    toward = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), -np.sin(el)])
    origin = np.asarray(target_O, dtype=float) - distance_mm * toward
    x = np.cross([0.0, 0.0, 1.0], toward)
    x /= np.linalg.norm(x)
    if camera_behind:
        x = -x
    y = np.cross(toward, x)
    return make_T(np.column_stack([x, y, toward]), origin)


def fan_index(p_S):
    """Fractional ray index of a point in the laser plane (rays evenly spaced in x at z_end)."""
    w = SENSORS.x_width_end_mm
    return (p_S[0] / p_S[2] * SENSORS.z_end_mm + w / 2) / (w / (SENSORS.points - 1))


def profiler(T_O_S, noise=QUIET, seed=3, sensor_id="S1"):
    return VirtualProfiler(sensor_id, T_B_O @ T_O_S, SENSORS, noise, seed)


def xz_to_O(T_O_S, xz_S):
    p_S = np.column_stack([xz_S[:, 0], np.zeros(len(xz_S)), xz_S[:, 1]])
    return apply(T_O_S, p_S)


def test_flat_plate_reproduces_plane_exactly_without_noise():
    hf = HeightField((120.0, 120.0), 0.25, 6.0)
    T_O_S = sensor_T_O_S([55.0, 62.0, 0.0], azimuth_deg=37.0)
    prof = profiler(T_O_S)
    trace = prof.trace(hf, T_B_O)
    T_S_O = invert(T_O_S)
    n_S = T_S_O[:3, 2]  # plate normal in S
    p0_S = T_S_O[:3, 3]  # a point of the plate plane in S
    t_expected = (n_S @ p0_S) / (prof.dirs_S @ n_S)
    assert np.all(trace.reason == VALID)
    np.testing.assert_allclose(trace.range_mm, t_expected, atol=1e-9)
    np.testing.assert_allclose(trace.cos_incidence, -(prof.dirs_S @ n_S), atol=1e-12)
    p = prof.scan(hf, T_B_O, 1.25, 17)
    assert p.valid.all() and p.counter == 17 and p.stamp_s == 1.25
    np.testing.assert_allclose(xz_to_O(T_O_S, p.xz_S)[:, 2], 0.0, atol=1e-9)
    np.testing.assert_allclose(p.intensity, -(prof.dirs_S @ n_S), atol=1e-6)


def test_flat_plate_line_fit_matches_geometry_within_noise():
    sigma = 0.05
    hf = HeightField((120.0, 120.0), 0.25, 6.0)
    T_O_S = sensor_T_O_S([60.0, 60.0, 0.0], azimuth_deg=210.0)
    prof = profiler(T_O_S, NoiseConfig(range_sigma_mm=sigma, min_intensity=0.0), seed=11)
    p = prof.scan(hf, T_B_O, 0.0, 0)
    assert p.valid.all()
    T_S_O = invert(T_O_S)
    n_S, p0_S = T_S_O[:3, 2], T_S_O[:3, 3]
    # the plate's trace in the laser plane y_S = 0:  n_x x + n_z z = n . p0
    slope_true = -n_S[0] / n_S[2]
    icpt_true = (n_S @ p0_S) / n_S[2]
    slope, icpt = np.polyfit(p.xz_S[:, 0], p.xz_S[:, 1], 1)
    assert abs(slope - slope_true) < 5e-4
    assert abs(icpt - icpt_true) < 0.01
    rng_meas = np.linalg.norm(p.xz_S, axis=1)
    resid = rng_meas - (n_S @ p0_S) / (prof.dirs_S @ n_S)
    assert 0.85 * sigma < resid.std() < 1.15 * sigma


def _step_field(h_mm=4.0, k=240):
    """Plate with a straight step: high (h) for columns < k, bare for columns >= k.

    The bilinear surface ramps between the centres of columns k-1 and k, so the step's top edge
    is the line x = (k - 0.5) * cell, z = h along y.
    """
    hf = HeightField((120.0, 120.0), 0.25, 6.0)
    heights = np.zeros(hf.shape)
    heights[:, :k] = h_mm
    hf.heights_mm = heights
    return hf, (k - 0.5) * hf.cell_mm


@pytest.mark.parametrize("camera_behind", [True, False])
def test_step_laser_and_camera_shadows_where_geometry_predicts(camera_behind):
    h = 4.0
    hf, x_top = _step_field(h)
    # looking from the high side across the edge, 45 degrees to it in azimuth
    T_O_S = sensor_T_O_S([66.0, 60.0, 0.0], azimuth_deg=45.0, camera_behind=camera_behind)
    prof = profiler(T_O_S)
    trace = prof.trace(hf, T_B_O)
    T_S_O = invert(T_O_S)
    o, n_fan = T_O_S[:3, 3], T_O_S[:3, 1]  # laser origin and fan-plane normal (y_S) in O
    cam_O = apply(T_O_S, [[0.0, SENSORS.camera_baseline_mm, 0.0]])[0]

    # laser boundary: the fan plane cuts the top edge line (x_top, y, h)
    y_p = o[1] - (n_fan[0] * (x_top - o[0]) + n_fan[2] * (h - o[2])) / n_fan[1]
    f_laser = fan_index(apply(T_S_O, [[x_top, y_p, h]])[0])
    # camera shadow end: floor point of the fan whose sight line to the camera grazes the edge
    x_q = x_top + h * (x_top - cam_O[0]) / (cam_O[2] - h)
    y_q = o[1] - (n_fan[0] * (x_q - o[0]) + n_fan[2] * (0.0 - o[2])) / n_fan[1]
    f_cam = fan_index(apply(T_S_O, [[x_q, y_q, 0.0]])[0])

    p = prof.scan(hf, T_B_O, 0.0, 0)
    np.testing.assert_array_equal(p.valid, trace.reason == VALID)
    z_O = np.full(SENSORS.points, np.nan)
    z_O[p.valid] = xz_to_O(T_O_S, p.xz_S[p.valid])[:, 2]
    top = np.flatnonzero(p.valid & (np.abs(z_O - h) < 1e-6))
    floor = np.flatnonzero(p.valid & (np.abs(z_O) < 1e-6))
    assert top.size > 50 and floor.size > 50
    assert top.size + floor.size == p.valid.sum()  # no point on the ramp (back-facing to laser)
    floor_side = np.sign(floor.mean() - f_laser)
    assert np.all(np.sign(top - f_laser) == -floor_side)
    nearest_top = top.max() if floor_side > 0 else top.min()
    assert abs(nearest_top - f_laser) <= 1.0

    idx = np.arange(SENSORS.points)
    beyond_edge = (idx - f_laser) * floor_side > 0
    before_q = (f_cam - idx) * floor_side > 0
    predicted_shadow = np.flatnonzero(beyond_edge & before_q)
    shadow = np.flatnonzero(trace.reason == CAMERA_SHADOW)
    assert np.all(trace.reason[trace.reason != CAMERA_SHADOW] == VALID)
    if camera_behind:
        assert predicted_shadow.size > 20  # the geometry really makes a camera shadow
        assert shadow.size and np.all(np.diff(shadow) == 1)
        assert abs(shadow.min() - predicted_shadow.min()) <= 1
        assert abs(shadow.max() - predicted_shadow.max()) <= 1
    else:
        assert predicted_shadow.size == 0 and shadow.size == 0


def _bearing_blocked(from_xy, to_xy, axis_xy, radius):
    """Whether the horizontal segment from -> to passes within ``radius`` of ``axis_xy``."""
    d = to_xy - from_xy
    s = np.clip(np.einsum("ij,ij->i", axis_xy - from_xy, d) / np.einsum("ij,ij->i", d, d),
                0.0, 1.0)
    closest = from_xy + s[:, None] * d
    return np.linalg.norm(closest - axis_xy, axis=1) < radius


def test_cylinder_blocks_laser_rays_where_tangent_lines_predict():
    hf = HeightField((120.0, 120.0), 0.25, 6.0)
    target = np.array([60.0, 60.0, 0.0])
    T_O_S = sensor_T_O_S(target, azimuth_deg=120.0)
    o = T_O_S[:3, 3]
    axis_O = o + 0.45 * (target - o)  # on the central ray, nearer the sensor
    radius = 6.0
    T_O_C = make_T(translation_mm=[axis_O[0], axis_O[1], 5.0])  # vertical, z 5..85 in O
    cyl = CylinderOccluder(T_B_O @ T_O_C, radius, 80.0, "post")
    prof = profiler(T_O_S)
    trace = prof.trace(hf, T_B_O, occluders=[cyl])
    # a ray is blocked iff its horizontal direction from the origin passes within the radius
    dirs_O = prof.dirs_S @ T_O_S[:3, :3].T
    far_xy = o[:2] + 200.0 * dirs_O[:, :2] / np.linalg.norm(dirs_O[:, :2], axis=1)[:, None]
    predicted = _bearing_blocked(np.broadcast_to(o[:2], far_xy.shape), far_xy, axis_O[:2], radius)
    blocked = trace.reason == LASER_BLOCKED
    assert predicted.sum() > 50
    mism = np.flatnonzero(blocked != predicted)
    assert mism.size <= 2
    edges = np.flatnonzero(np.diff(predicted.astype(int)))
    assert all(np.min(np.abs(edges - m)) <= 1 for m in mism)
    assert not prof.scan(hf, T_B_O, 0.0, 0, occluders=[cyl]).valid[predicted].any()


def test_cylinder_blocks_only_the_camera_where_sight_lines_predict():
    hf = HeightField((120.0, 120.0), 0.25, 6.0)
    target = np.array([60.0, 60.0, 0.0])
    T_O_S = sensor_T_O_S(target, azimuth_deg=300.0, camera_behind=True)
    prof = profiler(T_O_S)
    cam_O = apply(T_O_S, [[0.0, SENSORS.camera_baseline_mm, 0.0]])[0]
    # camera rays pass ~25 mm up at 40 mm from the target; laser rays there are ~57 mm up
    horiz = (target - cam_O)[:2] / np.linalg.norm((target - cam_O)[:2])
    axis_xy = target[:2] - 40.0 * horiz
    radius = 3.0
    cyl = CylinderOccluder(T_B_O @ make_T(translation_mm=[*axis_xy, 15.0]), radius, 20.0)
    trace = prof.trace(hf, T_B_O, occluders=[cyl])
    floor_pts = trace.points_O
    predicted = _bearing_blocked(np.broadcast_to(cam_O[:2], (SENSORS.points, 2)),
                                 floor_pts[:, :2], axis_xy, radius)
    blocked = trace.reason == CAMERA_BLOCKED
    assert predicted.sum() > 30 and not np.any(trace.reason == LASER_BLOCKED)
    mism = np.flatnonzero(blocked != predicted)
    edges = np.flatnonzero(np.diff(predicted.astype(int)))
    assert mism.size <= 2 and all(np.min(np.abs(edges - m)) <= 1 for m in mism)


def test_nozzle_occluder_runs_up_from_the_exit_against_the_spray():
    cell = CellConfig()
    exit_B = np.array(cell.nozzle_exit_B_mm)
    T_B_N = make_T(np.diag([1.0, -1.0, -1.0]), exit_B)  # +z_N = -z_B
    noz = nozzle_occluder(T_B_N, cell)
    r = cell.nozzle_body_diameter_mm / 2
    ex = np.array([1.0, 0.0, 0.0])
    origins = exit_B + np.array([[-100.0, 0.0, 100.0], [-100.0, 0.0, -1.0],
                                 [-100.0, 0.999 * r, 50.0], [-100.0, 1.001 * r, 50.0],
                                 [5.0, 0.0, 600.0], [-100.0, 0.0, cell.nozzle_length_mm + 1]])
    dirs = np.array([ex, ex, ex, ex, [0.0, 0.0, -1.0], ex])
    t = noz.hit_t(origins, dirs)
    assert t[0] == pytest.approx(100.0 - r, abs=1e-9)
    assert np.isinf(t[1])  # below the exit: the spray side is open
    assert np.isfinite(t[2]) and np.isinf(t[3])
    assert t[4] == pytest.approx(600.0 - cell.nozzle_length_mm, abs=1e-9)  # top cap
    assert np.isinf(t[5])


def test_measuring_range_and_intensity_floor():
    hf = HeightField((120.0, 120.0), 0.25, 6.0)
    near = profiler(sensor_T_O_S([60.0, 60.0, 0.0], distance_mm=60.0))
    far = profiler(sensor_T_O_S([60.0, 60.0, 0.0], distance_mm=150.0))
    assert np.all(near.trace(hf, T_B_O).reason == NO_SURFACE)
    assert np.all(far.trace(hf, T_B_O).reason == NO_SURFACE)
    p = far.scan(hf, T_B_O, 0.0, 0)
    assert not p.valid.any() and np.all(np.isnan(p.xz_S)) and np.all(p.intensity == 0)
    dark = profiler(sensor_T_O_S([60.0, 60.0, 0.0]), NoiseConfig(range_sigma_mm=0.0,
                                                                   min_intensity=0.81))
    tr = dark.trace(hf, T_B_O)
    assert 0 < np.sum(tr.cos_incidence < 0.81) < SENSORS.points
    assert np.all(tr.reason[tr.cos_incidence < 0.81] == TOO_DARK)
    assert np.all(tr.reason[tr.cos_incidence >= 0.81] == VALID)
