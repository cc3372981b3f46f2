"""Static cell model: nozzle, profilers, plate pose for a spray target, reach, config errors."""

import numpy as np
import pytest

from dm2.core import frames
from dm2.core.config import ConfigError, parse_scenario
from twin.cell import kinematics as kin
from twin.cell.cell import CellModel
from twin.schema import CellConfig

STANDOFF = 30.0


@pytest.fixture(scope="module")
def cell():
    return CellModel.from_config(CellConfig(), STANDOFF)


def test_nozzle_spot_and_sensors(cell):
    cfg = CellConfig()
    np.testing.assert_allclose(cell.T_B_N[:3, 2], [0.0, 0.0, -1.0])
    np.testing.assert_allclose(cell.spot_B, np.array(cfg.nozzle_exit_B_mm) - [0, 0, STANDOFF])
    az = []
    for T in cell.T_B_S.values():
        to_spot = cell.spot_B - T[:3, 3]
        assert np.linalg.norm(to_spot) == pytest.approx(cfg.sensor_distance_mm)
        np.testing.assert_allclose(T[:3, 2], to_spot / np.linalg.norm(to_spot), atol=1e-12)
        assert abs(T[2, 0]) < 1e-12  # laser fan horizontal
        elev = np.degrees(np.arcsin(-T[2, 2]))
        assert elev == pytest.approx(cfg.sensor_elevation_deg)
        az.append(np.degrees(np.arctan2(-to_spot[1], -to_spot[0])))
    np.testing.assert_allclose(np.sort(np.mod(az, 360.0)), np.sort(cfg.sensor_azimuth_deg))
    cal = cell.calibration()
    np.testing.assert_array_equal(cal.T_F_O, cell.T_F_O)
    np.testing.assert_array_equal(cal.T_B_N, cell.T_B_N)
    assert set(cal.T_B_S) == {"S1", "S2", "S3"}


def test_plate_pose_puts_target_on_spot_along_axis_without_spin(cell):
    rng = np.random.default_rng(5)
    p = rng.uniform([0, 0, 0], [120, 120, 20], (50, 3))
    tilt = np.deg2rad(rng.uniform(0, 35, 50))
    az = rng.uniform(0, 2 * np.pi, 50)
    a = np.c_[np.sin(tilt) * np.cos(az), np.sin(tilt) * np.sin(az), -np.cos(tilt)]
    T = cell.T_B_O_for(p, a)
    spot = np.einsum("nij,nj->ni", T[:, :3, :3], p) + T[:, :3, 3]
    np.testing.assert_allclose(spot, np.broadcast_to(cell.spot_B, spot.shape), atol=1e-9)
    np.testing.assert_allclose(np.einsum("nij,nj->ni", T[:, :3, :3], a),
                               np.broadcast_to(cell.T_B_N[:3, 2], a.shape), atol=1e-12)
    for k in range(50):
        # relative to the level plate the tilt turns about a horizontal axis only: no spin
        rv = frames.to_rotvec(frames.make_T(T[k, :3, :3] @ cell.R_B_O_level.T))[0]
        assert abs(rv[2]) < 1e-12
        assert np.linalg.norm(rv) == pytest.approx(tilt[k], abs=1e-9)
    level = cell.T_B_O_for([[60.0, 60.0, 0.0]], [[0.0, 0.0, -1.0]])[0]
    np.testing.assert_allclose(level[:3, :3], cell.R_B_O_level, atol=1e-15)


def test_whole_plate_reachable_tilted_35_deg_on_one_branch(cell):
    """A serpentine over the plate at every tilt direction: no limit, no wrist singularity."""
    xs = np.linspace(0.0, 120.0, 7)
    pts = [(x, y, z) for z in (0.0, 30.0) for i, y in enumerate(xs)
           for x in (xs if i % 2 == 0 else xs[::-1])]
    axes = [np.array([0.0, 0.0, -1.0])]
    for az in np.deg2rad(np.arange(0, 360, 30)):
        t = np.deg2rad(35.0)
        axes.append(np.array([np.sin(t) * np.cos(az), np.sin(t) * np.sin(az), -np.cos(t)]))
    P = np.repeat(np.array(pts), len(axes), axis=0)
    A = np.tile(np.array(axes), (len(pts), 1))
    Q, code, k = kin.ik_track(cell.T_B_F_for(P, A), cell.home_joints_rad, 0.0,
                              cell.wrist_singularity_rad)
    assert code == kin.OK, kin.FAILURE_TEXT.get(code)
    qd = np.degrees(Q)
    margin = np.minimum(qd - kin.JOINT_LIMITS_DEG[:, 0], kin.JOINT_LIMITS_DEG[:, 1] - qd)
    assert margin.min() > 10.0  # at least 10 deg clear of every joint limit
    assert np.abs(qd[:, 4]).min() > 15.0  # wrist well clear of its singularity
    T_back = cell.T_B_O_from_joints(Q)
    spot = np.einsum("nij,nj->ni", T_back[:, :3, :3], P) + T_back[:, :3, 3]
    assert np.abs(spot - cell.spot_B).max() < 1e-6


def _scenario(cell: dict) -> dict:
    return {"name": "t", "part": {"generator": "pad"}, "cell": cell}


@pytest.mark.parametrize("cell_section, field", [
    ({"accel_mm_s2": -5.0}, "cell.accel_mm_s2"),
    ({"nozzle_exit_B_mm": [1.0, 2.0]}, "cell.nozzle_exit_B_mm"),
    ({"nozzle_xyz": [1.0, 2.0, 3.0]}, "cell.nozzle_xyz"),
    ({"sensor_elevation_deg": 95.0}, "cell.sensor_elevation_deg"),
    ({"home_joints_deg": "up"}, "cell.home_joints_deg"),
])
def test_malformed_cell_section_names_field(cell_section, field):
    with pytest.raises(ConfigError, match=field.replace(".", r"\.")):
        parse_scenario(_scenario(cell_section), "bad.toml")


def test_cell_model_rejects_unreachable_geometry_naming_field():
    sc = parse_scenario(_scenario({"home_joints_deg": [0, 170, 0, 0, -60, 0]}), "bad.toml")
    with pytest.raises(ConfigError, match=r"cell\.home_joints_deg: axis 2"):
        CellModel.from_scenario(sc)
    sc = parse_scenario(_scenario({"nozzle_exit_B_mm": [4000.0, 0.0, 500.0]}), "bad.toml")
    with pytest.raises(ConfigError, match=r"cell\.nozzle_exit_B_mm"):
        CellModel.from_scenario(sc)


def test_pybullet_fk_matches_our_fk(cell):
    from twin.cell.pybullet_cell import URDF_PATH, PybulletCell, irb4600_urdf

    assert URDF_PATH.read_text(encoding="utf-8") == irb4600_urdf()
    rng = np.random.default_rng(11)
    with PybulletCell(cell) as pbc:
        for _ in range(40):
            q = rng.uniform(kin.JOINT_LIMITS_RAD[:, 0], kin.JOINT_LIMITS_RAD[:, 1])
            pbc.set_joints(q)
            dt, dr = frames.pose_error(pbc.flange_pose(), kin.fk(q))
            assert dt < 1e-6 and dr < 1e-9


def test_profilers_that_cannot_reach_the_spot_are_refused():
    import pytest as _pytest

    from dm2.core.config import ConfigError, parse_scenario
    from twin.cell.cell import CellModel

    sc = parse_scenario({"name": "x", "part": {"generator": "pad"},
                         "cell": {"sensor_distance_mm": 400.0}})
    with _pytest.raises(ConfigError, match="cell.sensor_distance_mm.*never see the part"):
        CellModel.from_scenario(sc)
