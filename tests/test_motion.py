"""Executed motion: IK/FK along a toolpath, trapezoidal speed, reversal residence, reach errors."""

import numpy as np
import pytest

from dm2.core.messages import Toolpath
from twin.cell import kinematics as kin
from twin.cell.cell import CellModel
from twin.cell.motion import execute_toolpath, plan_toolpath
from twin.cell.trajectory import sample_path
from twin.schema import CellConfig

ACCEL = 500.0
V = 30.0


@pytest.fixture(scope="module")
def cell():
    return CellModel.from_config(CellConfig(accel_mm_s2=ACCEL), 30.0)


def make_toolpath(points, axes=None, speed=V, zone=1.0, layer=None, kind=None) -> Toolpath:
    P = np.asarray(points, dtype=float)
    n = len(P)
    A = np.tile([0.0, 0.0, -1.0], (n, 1)) if axes is None else np.asarray(axes, float)
    return Toolpath(P, A, np.full(n, speed), np.zeros(n) if kind is None else kind,
                    np.zeros(n, int) if layer is None else layer, np.ones(n, bool),
                    np.full(n, zone))


def raster_contour_toolpath(n_layers=2) -> Toolpath:
    """Per layer: a 2 mm raster over 40 x 40 mm, then a 35 deg tilted circular contour."""
    P, A, K, Ly = [], [], [], []
    for layer in range(n_layers):
        z = 0.8 * layer
        for i in range(21):
            xs = (40.0, 80.0) if i % 2 == 0 else (80.0, 40.0)
            P += [(xs[0], 40.0 + 2 * i, z), (xs[1], 40.0 + 2 * i, z)]
            A += [(0.0, 0.0, -1.0)] * 2
            K += [0, 0]
        th = np.linspace(0.0, 2 * np.pi, 73)
        al = np.deg2rad(35.0)
        P += list(np.c_[60 + 25 * np.cos(th), 60 + 25 * np.sin(th), np.full(73, z)])
        A += list(np.c_[np.sin(al) * np.cos(th), np.sin(al) * np.sin(th),
                        np.full(73, -np.cos(al))])
        K += [1] * 73
        Ly += [layer] * (42 + 73)
    return make_toolpath(P, A, layer=np.array(Ly), kind=np.array(K))


@pytest.fixture(scope="module")
def executed(cell):
    tp = raster_contour_toolpath()
    return tp, execute_toolpath(tp, cell, rate_hz=250.0)


def _spot_and_axis_error(T_B_O, position_O, axis_O, cell):
    spot = np.einsum("nij,nj->ni", T_B_O[:, :3, :3], position_O) + T_B_O[:, :3, 3]
    ax = np.einsum("nij,nj->ni", T_B_O[:, :3, :3], axis_O)
    d_mm = np.linalg.norm(spot - cell.spot_B, axis=1)
    d_deg = np.degrees(np.arccos(np.clip(ax @ cell.T_B_N[:3, 2], -1.0, 1.0)))
    return d_mm, d_deg


def test_ik_fk_round_trip_along_whole_toolpath(executed, cell):
    tp, em = executed
    assert np.all(np.diff(em.t_s) == pytest.approx(0.004))
    np.testing.assert_allclose(em.T_B_F, kin.fk(em.joints_rad), atol=1e-12)
    np.testing.assert_allclose(em.T_B_O, em.T_B_F @ cell.T_F_O, atol=1e-12)
    d_mm, d_deg = _spot_and_axis_error(em.T_B_O, em.position_O, em.axis_O, cell)
    assert d_mm.max() <= 0.01 and d_deg.max() <= 0.01
    # the spray target runs along the polyline of the move in progress
    i = em.segment
    a, b = tp.position_O[np.maximum(i - 1, 0)], tp.position_O[i]
    ab = b - a
    u = np.clip(np.einsum("ij,ij->i", em.position_O - a, ab) /
                np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-300), 0, 1)
    assert np.abs(a + u[:, None] * ab - em.position_O).max() < 1e-9
    np.testing.assert_array_equal(em.layer, tp.layer[i])
    assert np.all(np.diff(em.segment) >= 0) and em.segment[-1] == len(tp) - 1
    assert em.layer[-1] == 1 and em.kind[-1] == 1
    # joints move continuously on one branch (axis 5 keeps its sign)
    assert np.all(np.sign(em.joints_rad[:, 4]) == np.sign(cell.home_joints_rad[4]))


def test_spray_point_and_axis_match_toolpath_at_vertices(executed, cell):
    tp, em = executed
    timing = plan_toolpath(tp, cell)
    pos, axis, *_ = sample_path(timing, em.vertex_time_s)
    np.testing.assert_allclose(pos, tp.position_O, atol=1e-9)
    np.testing.assert_allclose(axis, tp.axis_O, atol=1e-9)
    Q, code, _ = kin.ik_track(cell.T_B_F_for(pos, axis), cell.home_joints_rad)
    assert code == kin.OK
    d_mm, d_deg = _spot_and_axis_error(cell.T_B_O_from_joints(Q), tp.position_O, tp.axis_O, cell)
    assert d_mm.max() <= 0.01 and d_deg.max() <= 0.01
    assert np.all(np.diff(em.vertex_time_s) >= 0)


def test_trapezoidal_speed_respects_programmed_speed_and_acceleration(executed):
    tp, em = executed
    assert np.all(em.speed_mm_s <= tp.speed_mm_s[em.segment] + 1e-9)
    acc = np.diff(em.speed_mm_s) / em.dt_s
    assert np.abs(acc).max() <= ACCEL * (1 + 1e-9)
    assert np.abs(acc).max() > 0.9 * ACCEL  # it does use the acceleration
    # speeds integrate to the distance travelled (trapezoid rule is exact within a phase)
    ds = np.diff(em.arc_mm)
    assert np.abs(ds - 0.5 * (em.speed_mm_s[1:] + em.speed_mm_s[:-1]) * em.dt_s).max() < 3e-3
    chord = np.linalg.norm(np.diff(em.position_O, axis=0), axis=1)
    assert np.all(chord <= ds + 1e-9)  # corners cut chords short, never long
    same = np.diff(em.segment) == 0
    np.testing.assert_allclose(chord[same], ds[same], atol=1e-9)
    assert em.speed_mm_s[0] == 0.0 and em.speed_mm_s[-1] == 0.0
    assert em.speed_mm_s.max() == pytest.approx(V)


@pytest.mark.parametrize("zone", [0.0, 0.5, 1.0])
def test_reversal_residence_exceeds_straight_pass_by_model_prediction(cell, zone):
    step, margin = 2.0, 30.0
    tp = make_toolpath([(10, 50, 0), (90, 50, 0), (90, 50 + step, 0), (10, 50 + step, 0)],
                       zone=zone)
    em = execute_toolpath(tp, cell)
    s1 = 80.0  # arc length at the first corner
    t_in, t_out = np.interp([s1 - margin, s1 + step + margin], em.arc_mm, em.t_s)
    window = 2 * margin + step
    # Model: each 90 deg corner is blended with d = min(zone, step/2), radius R = d / tan(45)
    # and v_c = sqrt(a R), held over the arc length R * pi / 2 centred on the vertex; braking
    # into the first and accelerating out of the last slow stretch each cost
    # (V - v_c)^2 / (2 a V); the straight rest of the step between the slow stretches
    # (length l) is a trapezoid or triangle starting and ending at v_c.
    d = min(zone, step / 2)
    vc = np.sqrt(ACCEL * d)
    h = d * np.pi / 4  # half the blend arc
    extra = 2 * (V - vc) ** 2 / (2 * ACCEL * V)
    if d > 0:
        extra += 4 * h * (1 / vc - 1 / V)
    ell = step - 2 * h
    if ell > 0:
        vp = min(V, np.sqrt(ACCEL * ell + vc * vc))
        t_mid = 2 * (vp - vc) / ACCEL + (ell - (vp * vp - vc * vc) / ACCEL) / vp
        extra += t_mid - ell / V
    assert t_out - t_in - window / V == pytest.approx(extra, rel=1e-6, abs=1e-9)
    assert extra > 0.03  # measurably longer than a straight pass
    slow = (np.abs(em.arc_mm - s1) < h - 1e-6) | (np.abs(em.arc_mm - s1 - step) < h - 1e-6)
    if d > 0:
        np.testing.assert_allclose(em.speed_mm_s[slow], vc, rtol=1e-9)


def test_dwell_adds_a_stop_at_the_vertex(cell):
    tp = make_toolpath([(20, 60, 0), (60, 60, 0), (100, 60, 0)])
    plain = execute_toolpath(tp, cell)
    dwell = np.array([0.0, 0.4, 0.0])
    em = execute_toolpath(tp, cell, dwell=dwell)
    assert np.count_nonzero(em.dwelling) == pytest.approx(0.4 / em.dt_s, abs=1)
    np.testing.assert_allclose(em.position_O[em.dwelling], np.tile([60, 60, 0], (100, 1)))
    assert np.all(em.speed_mm_s[em.dwelling] == 0.0)
    # stopping costs the dwell plus braking to rest and accelerating again (2 ramps of v/2a)
    expected = 0.4 + 2 * V / (2 * ACCEL)
    assert em.duration_s - plain.duration_s == pytest.approx(expected, abs=2 * em.dt_s)


def test_unreachable_point_raises_reach_error_naming_index_and_layer(cell):
    pts = [(40, 60, 0), (80, 60, 0), (80, 62, 0.8), (40, 62, 0.8), (-1500.0, 62, 0.8)]
    tp = make_toolpath(pts, layer=np.array([0, 0, 1, 1, 1]), speed=200.0)
    with pytest.raises(kin.ReachError, match=r"toolpath index 4 \(layer 1\)") as info:
        execute_toolpath(tp, cell, check_joint_speed=False)
    assert info.value.index == 4 and info.value.layer == 1


def test_points_closer_than_the_path_resolution_are_one_point(cell):
    # a straight 40 mm line sampled every 0.7 mm, each sample doubled 0.2 um further on with a
    # sub-degree axis jitter (what sliced contours carry): the controller sees one straight move
    xs = np.arange(20.0, 60.0 + 1e-9, 0.7)
    pts = np.repeat(np.c_[xs, np.full(xs.size, 60.0), np.zeros(xs.size)], 2, axis=0)
    pts[1::2, 0] += 2e-4
    pts[1::2, 1] += 1e-4
    tilt = np.deg2rad(np.where(np.arange(pts.shape[0]) % 2 == 1, 0.5, 0.0))
    axes = np.c_[np.sin(tilt), np.zeros_like(tilt), -np.cos(tilt)]
    em = execute_toolpath(make_toolpath(pts, axes), cell)
    clean = execute_toolpath(make_toolpath(pts[::2]), cell)
    length = pts[-2, 0] - pts[0, 0]
    # accelerate to V, cruise, brake: one trapezoid, exactly as the clean line
    assert clean.duration_s == pytest.approx(length / V + V / ACCEL, abs=clean.dt_s)
    assert em.duration_s == pytest.approx(clean.duration_s, abs=em.dt_s)
    assert em.speed_mm_s.max() == pytest.approx(V, rel=1e-9)
    cruise = (em.arc_mm > V * V / (2 * ACCEL) + 0.01) & (em.arc_mm < em.arc_mm[-1] - 1.0)
    np.testing.assert_allclose(em.speed_mm_s[cruise], V, rtol=1e-9)
    # an exact repeat with a new axis is still a reorientation on the spot
    turn = make_toolpath([(20, 60, 0), (40, 60, 0), (40, 60, 0), (60, 60, 0)],
                         axes=[(0, 0, -1.0), (0, 0, -1.0), (np.sin(0.2), 0, -np.cos(0.2)),
                               (np.sin(0.2), 0, -np.cos(0.2))])
    assert execute_toolpath(turn, cell).duration_s > clean.duration_s + 0.1
