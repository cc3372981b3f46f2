"""Execute a toolpath as the robot controller would: timed path, IK, true plate poses.

:func:`execute_toolpath` plans the path timing (:mod:`twin.cell.trajectory`: zones, look-ahead,
trapezoidal speed, optional dwell), samples it at the controller rate (250 Hz like ABB EGM),
solves the arm's joints for every sample on one configuration branch (closed-form IK seeded by
the previous sample, see :mod:`twin.cell.kinematics`), and reports the true poses from forward
kinematics of those joints.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from dm2.core.messages import Toolpath
from dm2.core.tolerances import ROUNDING_SLACK
from twin.cell import kinematics as kin
from twin.cell.cell import CellModel
from twin.cell.trajectory import PathTiming, plan_path, sample_path

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ExecutedMotion:
    """The executed motion at a fixed sample spacing ``dt_s = 1 / rate_hz``.

    Attributes
    ----------
    t_s : (m,) float64 [s], sample times from 0
    position_O : (m, 3) float64 [mm], spray target (deposition spot) on the plate
    axis_O : (m, 3) float64, unit spray direction in O
    T_B_O : (m, 4, 4) float64, true plate pose ``T_B_F @ T_F_O``
    T_B_F : (m, 4, 4) float64, flange pose from forward kinematics of ``joints_rad``
    joints_rad : (m, 6) float64 [rad]
    segment : (m,) int64, toolpath index of the move in progress (or of the vertex dwelt at)
    layer : (m,) int32; kind : (m,) int8; spray_on : (m,) bool, of that toolpath index
    speed_mm_s : (m,) float64 [mm/s], actual path speed of the spray target over the plate
    arc_mm : (m,) float64 [mm], path length travelled
    dwelling : (m,) bool, stopped at a vertex for a requested dwell
    vertex_time_s : (n,) float64 [s], when each toolpath vertex is reached
    dt_s : float [s]
    """

    t_s: np.ndarray
    position_O: np.ndarray
    axis_O: np.ndarray
    T_B_O: np.ndarray
    T_B_F: np.ndarray
    joints_rad: np.ndarray
    segment: np.ndarray
    layer: np.ndarray
    kind: np.ndarray
    spray_on: np.ndarray
    speed_mm_s: np.ndarray
    arc_mm: np.ndarray
    dwelling: np.ndarray
    vertex_time_s: np.ndarray
    dt_s: float

    def __post_init__(self):
        m = self.t_s.shape[0]
        shapes = {"position_O": (m, 3), "axis_O": (m, 3), "T_B_O": (m, 4, 4),
                  "T_B_F": (m, 4, 4), "joints_rad": (m, 6), "segment": (m,), "layer": (m,),
                  "kind": (m,), "spray_on": (m,), "speed_mm_s": (m,), "arc_mm": (m,),
                  "dwelling": (m,)}
        for name, shape in shapes.items():
            arr = getattr(self, name)
            if arr.shape != shape:
                raise ValueError(f"ExecutedMotion.{name}: expected {shape}, got {arr.shape}")
            arr.setflags(write=False)

    def __len__(self) -> int:
        return int(self.t_s.shape[0])

    @property
    def duration_s(self) -> float:
        return float(self.t_s[-1]) if len(self) else 0.0


def plan_toolpath(toolpath: Toolpath, cell: CellModel, accel_mm_s2: float | None = None,
                  dwell: np.ndarray | None = None) -> PathTiming:
    """The controller's timing of ``toolpath`` (no IK); see :mod:`twin.cell.trajectory`."""
    if len(toolpath) == 0:
        raise ValueError("toolpath is empty")
    return plan_path(toolpath.position_O, toolpath.axis_O, toolpath.speed_mm_s,
                     toolpath.zone_mm, cell.accel_mm_s2 if accel_mm_s2 is None else accel_mm_s2,
                     cell.max_reorient_rad_s, dwell)


def execute_toolpath(toolpath: Toolpath, cell: CellModel, rate_hz: float = 250.0,
                     accel_mm_s2: float | None = None, dwell: np.ndarray | None = None,
                     check_joint_speed: bool = True) -> ExecutedMotion:
    """Run ``toolpath`` on the cell's arm and sample the motion at ``rate_hz``.

    Parameters
    ----------
    toolpath : Toolpath, in the plate frame O
    cell : CellModel
    rate_hz : float [Hz], controller sample rate
    accel_mm_s2 : float [mm/s^2], path acceleration limit (default ``cell.accel_mm_s2``)
    dwell : (n,) float64 [s], extra stop at each toolpath vertex (None: none)
    check_joint_speed : bool, raise when a joint would exceed its datasheet speed

    Raises
    ------
    ReachError
        A sample cannot be reached (out of reach, joint limit, wrist singularity, joint speed);
        the message names the toolpath index and layer.
    """
    if not rate_hz > 0:
        raise ValueError(f"rate_hz must be > 0, got {rate_hz}")
    timing = plan_toolpath(toolpath, cell, accel_mm_s2, dwell)
    dt = 1.0 / rate_hz
    m = int(np.ceil(timing.duration_s / dt - ROUNDING_SLACK)) + 1
    t = np.arange(m) * dt
    pos, axis, speed, arc, kept, dwelling = sample_path(timing, t)
    segment = np.where(dwelling, timing.group_last[kept], timing.vertex_index[kept])
    T_B_O_target = cell.T_B_O_for(pos, axis)
    T_F_O_inv = np.linalg.inv(cell.T_F_O)
    T_B_F_target = T_B_O_target @ T_F_O_inv[None]
    joints, code, k = kin.ik_track(T_B_F_target, cell.home_joints_rad,
                                   dt if check_joint_speed else 0.0, cell.wrist_singularity_rad)
    if code != kin.OK:
        i = int(segment[k])
        layer = int(toolpath.layer[i])
        raise kin.ReachError(
            f"toolpath index {i} (layer {layer}) at t = {t[k]:.3f} s, point "
            f"{np.round(pos[k], 3).tolist()} mm in O: {kin.FAILURE_TEXT[code]}",
            index=i, layer=layer)
    T_B_F = kin.fk(joints)
    vertex_time = np.empty(len(toolpath))
    group = np.repeat(np.arange(timing.vertex_index.size),
                      timing.group_last - timing.vertex_index + 1)
    vertex_time[:] = timing.arrive_s[group]
    log.debug("executed %d toolpath points in %.1f s (%d samples)", len(toolpath),
              timing.duration_s, m)
    return ExecutedMotion(
        t_s=t, position_O=pos, axis_O=axis, T_B_O=T_B_F @ cell.T_F_O[None], T_B_F=T_B_F,
        joints_rad=joints, segment=segment.astype(np.int64), layer=toolpath.layer[segment],
        kind=toolpath.kind[segment], spray_on=toolpath.spray_on[segment],
        speed_mm_s=speed, arc_mm=arc, dwelling=dwelling, vertex_time_s=vertex_time, dt_s=dt)
