"""The calibration rehearsal is rendered by the twin's own profilers, from a prior that is the
cell file; touch-off, intrinsic errors and the calibration file's provenance."""

from __future__ import annotations

import numpy as np
import pytest

from calib.artifact import load_artifact
from calib.scan_model import FanModel
from calib.touch_off import nozzle_exit_from_touches, touch_off_from_toml, touch_off_to_toml
from dm2.core.calibration_io import calibration_from_toml, calibration_to_toml
from dm2.core.config import ConfigError, load_scenario
from dm2.core.frames import apply, from_rotvec, invert, pose_error
from dm2.core.messages import Profile, RobotState
from scenarios import resolve_scenario, scenario_dir
from twin.cell.cell import CellModel
from twin.profiler.intrinsics import IntrinsicError
from twin.profiler.sensor import fan_directions_S
from twin.schema import NoiseConfig
from twin.stream.rehearsal import RehearsalConfig, rehearse_calibration
from twin.stream.touch_off import touch_off_poses


@pytest.fixture(scope="module")
def scenario():
    return load_scenario(resolve_scenario("pad"))


@pytest.fixture(scope="module")
def artifact():
    return load_artifact(scenario_dir() / "artifacts" / "four_spheres.toml")


def _along_ray_residuals(sim):
    """Per valid point: measured range minus the true surface's distance along the same ray
    (the twin's truth; robot repeatability off, so the reported flange pose is the true one).
    Returns the residuals [mm] in profile order and the valid count per profile."""
    poses = {}
    for m in sim.messages:
        if isinstance(m, RobotState):
            poses[int(np.floor(m.stamp_s / 0.2 + 1e-9))] = m.T_B_F  # hold_s = 0.2 s a pose
    res, counts = [], []
    for p in (m for m in sim.messages if isinstance(m, Profile)):
        T_A_S = invert(poses[p.counter] @ sim.true_T_F_A) @ sim.truth.T_B_S[p.sensor_id]
        xz = p.xz_S[p.valid]
        p_S = np.column_stack([xz[:, 0], np.zeros(len(xz)), xz[:, 1]])
        rng_mm = np.linalg.norm(p_S, axis=1)
        d_A = (p_S / rng_mm[:, None]) @ T_A_S[:3, :3].T
        o_A = np.broadcast_to(T_A_S[:3, 3], d_A.shape)
        res.append(rng_mm - sim.surface.raycast(o_A, d_A))
        counts.append(len(xz))
    return np.concatenate(res), np.array(counts)


def _rehearse(scenario, artifact, **noise):
    cfg = RehearsalConfig(n_poses=6, seed=3, noise=NoiseConfig(**{"range_sigma_mm": 0.0,
                                                                    **noise}),
                          robot_repeatability_mm=0.0, touch_offs=0)
    return rehearse_calibration(scenario, artifact, cfg)


def test_rehearsal_profiles_follow_the_twin_profiler_noise(scenario, artifact):
    exact, n_exact = _along_ray_residuals(_rehearse(scenario, artifact))
    assert n_exact.sum() > 2000
    assert np.max(np.abs(exact)) < 1e-9  # the twin's ray cast of the artifact, no noise
    gauss, n_gauss = _along_ray_residuals(_rehearse(scenario, artifact, range_sigma_mm=0.03))
    assert abs(n_gauss.sum() - n_exact.sum()) <= 3  # a few noisy points leave the range
    assert np.std(gauss) == pytest.approx(0.03, rel=0.1) and abs(np.mean(gauss)) < 0.003
    speckle, _ = _along_ray_residuals(_rehearse(scenario, artifact, speckle_sigma_mm=0.02))
    assert np.std(speckle) == pytest.approx(0.02, rel=0.25)
    # speckle is correlated along the line (4 points), unlike the range noise
    lag1 = np.corrcoef(speckle[:-1], speckle[1:])[0, 1]
    assert lag1 > 0.7 and abs(np.corrcoef(gauss[:-1], gauss[1:])[0, 1]) < 0.1
    dropped, n_drop = _along_ray_residuals(_rehearse(scenario, artifact, dropout_prob=0.2))
    assert n_drop.sum() / n_exact.sum() == pytest.approx(0.8, abs=0.03)
    assert np.max(np.abs(dropped)) < 1e-9  # the points that remain are untouched
    ghosts, n_ghost = _along_ray_residuals(_rehearse(scenario, artifact, outlier_prob=0.05,
                                                     outlier_offset_mm=(1.0, 4.0)))
    far = np.abs(ghosts) > 1e-6
    assert far.mean() == pytest.approx(0.05, abs=0.015)
    assert np.all((ghosts[far] >= 1.0 - 1e-9) & (ghosts[far] <= 4.0 + 1e-9))  # beyond


def test_calib_fan_is_the_sensor_fan(scenario):
    d_calib = FanModel.from_config(scenario.sensors).ray_dirs_S()
    d_twin = fan_directions_S(scenario.sensors)
    assert np.array_equal(d_calib, d_twin)
    x_at_end = d_calib[:, 0] / d_calib[:, 2] * scenario.sensors.z_end_mm
    assert np.allclose(np.diff(x_at_end), scenario.sensors.x_width_end_mm
                       / (scenario.sensors.points - 1))  # even in x, not in angle


def test_prior_is_the_cell_file_and_the_truth_is_the_cell_as_built(scenario, artifact):
    sim = _rehearse(scenario, artifact)
    nominal = CellModel.from_scenario(scenario).calibration()
    for sid in ("S1", "S2", "S3"):
        assert np.array_equal(sim.prior.T_B_S[sid], nominal.T_B_S[sid])
        dt, dr = pose_error(sim.truth.T_B_S[sid], nominal.T_B_S[sid])
        assert dt == pytest.approx(2.0, abs=1e-9) and np.degrees(dr) == pytest.approx(1.0)
    # the artifact as built lies within its certificate, and is not the certified one
    dr = sim.surface.radii_mm - artifact.radii_mm
    dc = sim.surface.centers_A - artifact.centers_A
    assert 0 < np.max(np.abs(dr)) <= artifact.radius_uncertainty_mm
    assert 0 < np.max(np.abs(dc)) <= artifact.position_uncertainty_mm


def test_touch_off_finds_the_nozzle_exit(scenario, artifact):
    cell = CellModel.from_scenario(scenario)
    true_T_B_N = cell.T_B_N @ from_rotvec([0, 0, 0], [0.7, -0.4, 0.3])
    rng = np.random.default_rng(0)
    touches = touch_off_poses(artifact.touch_mark_A, cell.T_F_O, true_T_B_N, np.eye(3), 6,
                              rng, 0.01, 0.02 / 3.62, lambda T: True)
    # every touch seats the mark on the exit (up to the seat and robot errors)
    seats = np.stack([apply(T @ cell.T_F_O, artifact.touch_mark_A[None])[0] for T in touches])
    assert np.max(np.linalg.norm(seats - true_T_B_N[:3, 3], axis=1)) < 0.06
    back = touch_off_from_toml(touch_off_to_toml(touches))
    assert np.allclose(back, touches, atol=1e-12)
    est = nozzle_exit_from_touches(back, cell.T_F_O, artifact.touch_mark_A, cell.T_B_N)
    assert np.linalg.norm(est.T_B_N[:3, 3] - true_T_B_N[:3, 3]) < 0.02
    assert np.array_equal(est.T_B_N[:3, :3], cell.T_B_N[:3, :3])  # the axis is the prior's
    assert np.all(est.scatter_mm < 0.03) and est.n_touches == 6


def test_intrinsic_error_moves_reported_points_as_documented(scenario):
    sn = scenario.sensors
    xz = np.array([[0.0, 100.0], [20.0, 110.0], [-25.0, 90.0], [np.nan, np.nan]])
    z_only = IntrinsicError(z_scale_error=0.001).reported_xz(xz, sn)
    assert np.allclose(z_only[:3], xz[:3] * [1.0, 1.001]) and np.all(np.isnan(z_only[3]))
    fan = IntrinsicError(fan_angle_offset_rad=np.radians(0.05)).reported_xz(xz, sn)
    theta = np.arctan2(xz[:3, 0], xz[:3, 1]) + np.radians(0.05)
    assert np.allclose(fan[:3, 0], xz[:3, 1] * np.tan(theta)) and np.allclose(fan[:3, 1],
                                                                              xz[:3, 1])
    edge = np.array([[0.5 * sn.x_width_end_mm, sn.z_end_mm]])
    dist = IntrinsicError(x_distortion_mm=0.03).reported_xz(edge, sn)
    assert dist[0, 0] - edge[0, 0] == pytest.approx(0.03)  # worth 0.03 mm at the fan's edge


def test_calibration_file_records_provenance(scenario):
    cal = CellModel.from_scenario(scenario).calibration()
    prov = {"T_B_N": "taken from the cell file", "T_F_O": "estimated: artifact mount",
            "S1": "estimated: solve", "S2": "estimated: solve", "S3": "estimated: solve"}
    text = calibration_to_toml(cal, prov)
    back = calibration_from_toml(text)
    assert np.allclose(back.T_B_S["S2"], cal.T_B_S["S2"])
    assert 'T_B_N = "taken from the cell file"' in text
    with pytest.raises(ConfigError, match=r"provenance.T_F_O': 'guessed' does not start"):
        calibration_from_toml(text.replace('"estimated: artifact mount"', '"guessed"'), "c.toml")
    with pytest.raises(ConfigError, match=r"c.toml: field 'provenance': missing S3"):
        calibration_from_toml(text.replace('S3 = "estimated: solve"\n', ""), "c.toml")
