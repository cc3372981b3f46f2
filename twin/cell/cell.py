"""The static cell: arm, stationary cold-spray nozzle, three profilers, plate on the flange.

Plain numpy (no pybullet): poses of everything that does not move, plus the mapping from a
toolpath point and spray axis to the plate pose the arm must hold. The cell's state (joints,
time) lives elsewhere (:mod:`twin.cell.motion`).

Conventions (see ARCHITECTURE.md, "Frames and units"):

- ``T_B_N``: nozzle exit at ``cell.nozzle_exit_B_mm``, ``+z_N = -z_B`` (spray straight down),
  ``x_N = x_B``. The deposition spot is ``standoff_mm`` along ``+z_N`` from the exit.
- ``T_F_O``: plate corner on the flange from ``cell.plate_on_flange_mm`` and
  ``cell.plate_on_flange_rpy_deg`` (fixed-axis roll, pitch, yaw as in URDF: Rz(y) Ry(p) Rx(r)).
- ``T_B_S[j]``: profiler j sits ``sensor_distance_mm`` from the spot, ``sensor_elevation_deg``
  above the horizontal plane through the spot, at azimuth ``sensor_azimuth_deg[j]`` measured
  about ``+z_B`` from ``+x_B``; ``+z_S`` aims at the spot and ``x_S`` (the laser fan) is
  horizontal, ``x_S = z_B x z_S`` normalised.
- Plate pose for a toolpath point ``p_O`` and spray axis ``a_O``: ``T_B_O @ p_O = spot_B`` and
  ``R_B_O @ a_O = z_N``. The rotation about the spray axis is free; it is fixed by tilting the
  level plate (``z_O = z_B``, ``x_O`` at ``cell.work_yaw_deg`` about ``z_B``) by the smallest
  rotation that brings ``a_O`` onto ``-z_O``'s level direction, so the plate never spins.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from dm2.core import frames
from dm2.core.config import ConfigError
from dm2.core.messages import SENSOR_IDS, Calibration
from dm2.core.tolerances import ROUNDING_SLACK
from twin.cell import kinematics as kin


def minimal_rotations(from_unit: np.ndarray, to_unit: np.ndarray) -> np.ndarray:
    """Smallest rotations taking each ``from_unit[i]`` onto ``to_unit`` (Rodrigues, vectorised).

    Parameters
    ----------
    from_unit : (n, 3) float64 unit vectors
    to_unit : (3,) float64 unit vector

    Returns
    -------
    (n, 3, 3) float64 rotation matrices
    """
    a = np.asarray(from_unit, dtype=np.float64)
    b = np.asarray(to_unit, dtype=np.float64)
    v = np.cross(a, b)
    c = a @ b
    if np.any(c < -1.0 + ROUNDING_SLACK):
        raise ValueError("minimal_rotations: a direction is opposite to the target direction")
    K = np.zeros((a.shape[0], 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -v[:, 2], v[:, 1], -v[:, 0]
    K[:, 1, 0], K[:, 2, 0], K[:, 2, 1] = v[:, 2], -v[:, 1], v[:, 0]
    f = (1.0 / (1.0 + c))[:, None, None]
    return np.eye(3)[None] + K + f * (K @ K)


@dataclass(frozen=True)
class CellModel:
    """Fixed geometry of the cell [mm, rad].

    Attributes
    ----------
    T_B_N : (4, 4) nozzle exit in the base; ``+z_N`` is the spray direction
    T_F_O : (4, 4) plate corner (work object) on the flange
    T_B_S : dict sensor id -> (4, 4) profiler poses in the base
    plate_size_mm : (3,) plate length x, length y, thickness
    spot_B : (3,) deposition spot in the base (``standoff_mm`` below the nozzle exit)
    standoff_mm : float, nozzle exit to deposition spot
    nozzle_exit_B : (3,) nozzle exit centre in the base
    nozzle_length_mm, nozzle_body_diameter_mm : float, the occluding nozzle body above the exit
    R_B_O_level : (3, 3) plate orientation for a vertical spray axis (reference, no spin)
    home_joints_rad : (6,) configuration the arm starts from (picks the IK branch)
    accel_mm_s2 : float, path acceleration limit
    max_reorient_rad_s : float, spray-axis reorientation rate limit
    wrist_singularity_rad : float, smallest allowed ``|q5|``
    robot_state_hz : float, controller state rate (EGM)
    """

    T_B_N: np.ndarray
    T_F_O: np.ndarray
    T_B_S: dict
    plate_size_mm: np.ndarray
    spot_B: np.ndarray
    standoff_mm: float
    nozzle_exit_B: np.ndarray
    nozzle_length_mm: float
    nozzle_body_diameter_mm: float
    R_B_O_level: np.ndarray
    home_joints_rad: np.ndarray
    accel_mm_s2: float
    max_reorient_rad_s: float
    wrist_singularity_rad: float
    robot_state_hz: float

    @classmethod
    def from_scenario(cls, scenario) -> CellModel:
        """Build from a ``dm2.core.config.Scenario`` (uses its ``cell``, ``process`` and ``sensors``
        sections).

        Raises
        ------
        ConfigError
            As :meth:`from_config`, or a profiler whose measuring range does not reach the
            deposition spot it is aimed at (it would never see the part).
        """
        cell, sensors = scenario.cell, scenario.sensors
        if not sensors.z_start_mm <= cell.sensor_distance_mm <= sensors.z_end_mm:
            raise ConfigError(
                f"cell.sensor_distance_mm: the profilers stand {cell.sensor_distance_mm} mm "
                f"from the deposition spot, outside their measuring range "
                f"[{sensors.z_start_mm}, {sensors.z_end_mm}] mm (sensors.z_start_mm .. "
                f"sensors.z_end_mm): they would never see the part")
        return cls.from_config(cell, scenario.process.standoff_mm)

    @classmethod
    def from_config(cls, cell, standoff_mm: float) -> CellModel:
        """Build from a ``twin.schema.CellConfig`` and the spray standoff [mm].

        Raises
        ------
        ConfigError
            The home joints lie outside the joint limits, or the deposition spot cannot be
            reached with the level plate.
        """
        exit_B = np.asarray(cell.nozzle_exit_B_mm, dtype=np.float64)
        T_B_N = frames.make_T(np.diag([1.0, -1.0, -1.0]), exit_B)
        spot_B = exit_B + standoff_mm * T_B_N[:3, 2]
        T_F_O = frames.make_T(Rotation.from_euler("xyz", cell.plate_on_flange_rpy_deg,
                                                  degrees=True), cell.plate_on_flange_mm)
        T_B_S = {}
        for sid, az in zip(SENSOR_IDS, cell.sensor_azimuth_deg, strict=True):
            az_r, el_r = np.deg2rad(az), np.deg2rad(cell.sensor_elevation_deg)
            d = np.array([np.cos(el_r) * np.cos(az_r), np.cos(el_r) * np.sin(az_r), np.sin(el_r)])
            T_B_S[sid] = frames.look_at(spot_B + cell.sensor_distance_mm * d, spot_B,
                                        up_hint=(0.0, 0.0, -1.0))
        home = np.deg2rad(np.asarray(cell.home_joints_deg, dtype=np.float64))
        lim = kin.JOINT_LIMITS_RAD
        for j in range(6):
            if not lim[j, 0] <= home[j] <= lim[j, 1]:
                raise ConfigError(
                    f"cell.home_joints_deg: axis {j + 1} = {cell.home_joints_deg[j]} deg lies "
                    f"outside its limits [{kin.JOINT_LIMITS_DEG[j, 0]:g}, "
                    f"{kin.JOINT_LIMITS_DEG[j, 1]:g}] deg")
        model = cls(
            T_B_N=T_B_N, T_F_O=T_F_O, T_B_S=T_B_S,
            plate_size_mm=np.asarray(cell.plate_size_mm, dtype=np.float64),
            spot_B=spot_B, standoff_mm=float(standoff_mm), nozzle_exit_B=exit_B,
            nozzle_length_mm=float(cell.nozzle_length_mm),
            nozzle_body_diameter_mm=float(cell.nozzle_body_diameter_mm),
            R_B_O_level=Rotation.from_euler("z", cell.work_yaw_deg, degrees=True).as_matrix(),
            home_joints_rad=home, accel_mm_s2=float(cell.accel_mm_s2),
            max_reorient_rad_s=float(np.deg2rad(cell.max_reorient_deg_s)),
            wrist_singularity_rad=float(np.deg2rad(cell.wrist_singularity_deg)),
            robot_state_hz=float(cell.robot_state_hz))
        centre_O = np.array([[model.plate_size_mm[0] / 2, model.plate_size_mm[1] / 2, 0.0]])
        T_B_F = model.T_B_F_for(centre_O, np.array([[0.0, 0.0, -1.0]]))[0]
        try:
            model.ik(T_B_F, home)
        except kin.ReachError as exc:
            raise ConfigError(
                f"cell.nozzle_exit_B_mm / cell.plate_on_flange_mm: the arm cannot hold the "
                f"plate centre at the deposition spot {np.round(spot_B, 1).tolist()} mm: "
                f"{exc}") from None
        return model

    def T_B_O_for(self, position_O: np.ndarray, axis_O: np.ndarray) -> np.ndarray:
        """Plate poses ``(n, 4, 4)`` putting each ``position_O`` at the spot along ``axis_O``.

        Parameters
        ----------
        position_O : (n, 3) float64 [mm], spray targets on the plate / part
        axis_O : (n, 3) float64, unit spray directions (nozzle towards surface) in O
        """
        p = np.asarray(position_O, dtype=np.float64).reshape(-1, 3)
        a = np.asarray(axis_O, dtype=np.float64).reshape(-1, 3)
        if p.shape != a.shape:
            raise ValueError(f"T_B_O_for: position_O {p.shape} and axis_O {a.shape} disagree")
        a = a / np.linalg.norm(a, axis=1, keepdims=True)
        # Tilt in O taking a_O onto (0, 0, -1), then place the level plate in B.
        R_O_level_O = minimal_rotations(a, np.array([0.0, 0.0, -1.0]))
        R = self.R_B_O_level[None] @ R_O_level_O
        T = np.zeros((p.shape[0], 4, 4))
        T[:, :3, :3] = R
        T[:, :3, 3] = self.spot_B[None] - np.einsum("nij,nj->ni", R, p)
        T[:, 3, 3] = 1.0
        return T

    def T_B_F_for(self, position_O: np.ndarray, axis_O: np.ndarray) -> np.ndarray:
        """Flange poses ``(n, 4, 4)`` for toolpath points (see :meth:`T_B_O_for`)."""
        return self.T_B_O_for(position_O, axis_O) @ frames.invert(self.T_F_O)[None]

    def ik(self, T_B_F: np.ndarray, seed_joints: np.ndarray | None = None) -> np.ndarray:
        """Joints (6,) [rad] for one flange pose, nearest ``seed_joints`` (default: home)."""
        seed = self.home_joints_rad if seed_joints is None else seed_joints
        return kin.ik(T_B_F, seed, self.wrist_singularity_rad)

    def T_B_O_from_joints(self, joints_rad: np.ndarray) -> np.ndarray:
        """True plate pose(s) ``fk(q) @ T_F_O``: joints (6,) -> (4, 4), (m, 6) -> (m, 4, 4)."""
        return kin.fk(joints_rad) @ self.T_F_O

    def calibration(self) -> Calibration:
        """The true calibration of this cell."""
        return Calibration(T_B_S={k: v.copy() for k, v in self.T_B_S.items()},
                           T_F_O=self.T_F_O.copy(), T_B_N=self.T_B_N.copy())
