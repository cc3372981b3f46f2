"""Fault schedule: feed/efficiency/standoff models, blobs, corner dwell, calibration error."""

from __future__ import annotations

import math

import numpy as np
import pytest

from dm2.core.config import ProcessConfig
from dm2.core.frames import from_euler_deg, invert
from dm2.core.messages import Calibration, Toolpath
from twin.schema import CalibrationPerturbation, FaultConfig
from twin.world.deposition import SprayModel
from twin.world.faults import FaultSchedule, find_corners, perturbed_calibration
from twin.world.heightfield import HeightField

DT = 1.0 / 250.0


def _raster(layer, z, speed=30.0):
    ys = np.arange(12.0, 28.0 + 1e-9, 2.0)
    pts = []
    for k, y in enumerate(ys):
        xa, xb = (12.0, 28.0) if k % 2 == 0 else (28.0, 12.0)
        pts += [(xa, y), (xb, y)]
    pts = np.array(pts)
    if layer % 2:
        pts = pts[:, ::-1]
    s = np.concatenate([[0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
    q = np.arange(0, s[-1], speed * DT)
    return np.column_stack([np.interp(q, s, pts[:, 0]), np.interp(q, s, pts[:, 1]),
                            np.full(len(q), z)])


def _build_pad(faults, n_layers=8, seed=3):
    p = ProcessConfig()
    sched = FaultSchedule(faults)
    hf = HeightField((40.0, 40.0), 0.5, 6.0)
    model = SprayModel(p, seed=seed)
    t = 0.0
    by_layer = []
    for layer in range(n_layers):
        spots = _raster(layer, 0.5 * layer)
        ts = t + DT * np.arange(len(spots))
        model.deposit_samples(hf, spots, np.tile([0.0, 0.0, -1.0], (len(spots), 1)), DT,
                              feed_factor=sched.feed_factor(ts, layer),
                              efficiency_factor=sched.efficiency_factor(layer),
                              standoff_delta_mm=sched.standoff_delta_mm(ts, layer))
        sched.apply_blobs(hf, layer)
        t = ts[-1] + DT
        by_layer.append(hf.copy())
    return by_layer


def _centre(hf):
    x, y = hf.centres_mm()
    return hf.heights_mm[np.ix_((y > 16) & (y < 24), (x > 16) & (x < 24))]


def test_feed_drop_over_layers_3_to_5_gives_expected_deficit():
    nominal = _build_pad(())
    faulty = _build_pad((FaultConfig(kind="feed_drop", layers=(3, 5), factor=0.5),))
    # identical until the fault starts (same seed, same draws)
    assert np.array_equal(nominal[2].heights_mm, faulty[2].heights_mm)
    gain = _centre(nominal[-1]).mean() / len(nominal)  # mean height per layer
    expected = 0.5 * 3 * gain
    deficit = _centre(nominal[-1]).mean() - _centre(faulty[-1]).mean()
    assert deficit == pytest.approx(expected, rel=0.10)
    # the deficit appears during layers 3-5 and then stays
    d = [_centre(n).mean() - _centre(f).mean() for n, f in zip(nominal, faulty, strict=True)]
    assert d[3] == pytest.approx(0.5 * gain, rel=0.2)
    assert d[5] == pytest.approx(expected, rel=0.1) and d[7] == pytest.approx(d[5], rel=0.1)


def test_feed_and_efficiency_and_standoff_profiles():
    s = FaultSchedule((
        FaultConfig(kind="feed_step", time_s=(10.0, 20.0), factor=0.8),
        FaultConfig(kind="feed_drift", layers=(2, 3), factor=0.5),
        FaultConfig(kind="clog", time_s=(100.0, 110.0), factor=0.2),
        FaultConfig(kind="efficiency_drift", layers=(4, 6), per_layer=0.1),
        FaultConfig(kind="standoff_change", time_s=(5.0, 6.0), delta_mm=4.0),
    ))
    assert s.feed_factor(5.0, 0) == 1.0
    assert s.feed_factor(15.0, 0) == pytest.approx(0.8)
    assert s.feed_factor(50.0, 0) == pytest.approx(0.8)  # a step stays
    assert s.feed_factor(50.0, 2) == pytest.approx(0.8 * 0.875)  # drift 1/4 through
    assert s.feed_factor(50.0, 3) == pytest.approx(0.8 * 0.625)
    assert s.feed_factor(50.0, 9) == pytest.approx(0.8 * 0.5)  # drift holds its end value
    assert s.feed_factor(105.0, 0) == pytest.approx(0.8 * 0.2)  # clog at its deepest
    assert s.feed_factor(111.0, 0) == pytest.approx(0.8)  # and recovered
    np.testing.assert_allclose(s.feed_factor(np.array([5.0, 15.0]), 0), [1.0, 0.8])
    np.testing.assert_allclose(s.efficiency_factor(np.arange(9)),
                               [1, 1, 1, 1, 1.1, 1.2, 1.3, 1.3, 1.3])
    assert s.standoff_delta_mm(5.5, 0) == 4.0 and s.standoff_delta_mm(7.0, 0) == 0.0
    with pytest.raises(ValueError, match=r"faults\[0\] \(kind 'feed_drop'\): missing factor"):
        FaultSchedule((FaultConfig(kind="feed_drop", layers=(1, 2)),))


def test_bump_and_dent_blobs_have_their_height_and_width():
    s = FaultSchedule((
        FaultConfig(kind="bump", layers=(2, 2), center_O_mm=(10.0, 12.0), height_mm=1.5,
                    width_mm=4.0),
        FaultConfig(kind="dent", layers=(3, 3), center_O_mm=(30.0, 20.0), height_mm=0.7,
                    width_mm=6.0),
    ))
    hf = HeightField((40.0, 40.0), 0.25)
    assert s.apply_blobs(hf, 1) == 0
    assert s.apply_blobs(hf, 2) == 1
    assert hf.height_at([[10.0, 12.0]])[0] == pytest.approx(1.5, rel=1e-2)
    assert hf.height_at([[12.0, 12.0]])[0] == pytest.approx(0.75, rel=1e-2)  # FWHM 4 mm
    s.apply_blobs(hf, 3)
    assert hf.height_at([[30.0, 20.0]])[0] == pytest.approx(-0.7, rel=1e-2)
    assert hf.height_at([[30.0, 23.0]])[0] == pytest.approx(-0.35, rel=1e-2)
    # the blob volume is peak * 2 pi sigma^2
    sig = 4.0 / (2 * math.sqrt(2 * math.log(2)))
    pos = hf.heights_mm[hf.heights_mm > 0].sum() * 0.25**2
    assert pos == pytest.approx(1.5 * 2 * math.pi * sig**2, rel=1e-3)


def _polygon_path(angles_deg, side=20.0, zone=1.0, layers=2):
    """Open polygon contour with the given interior angles, each corner rounded by a quadratic
    Bezier blend from ``zone`` before to ``zone`` after the sharp vertex."""
    turn = np.radians(180.0 - np.asarray(angles_deg, dtype=float))
    heading = np.concatenate([[0.0], np.cumsum(turn)])
    dirs = np.column_stack([np.cos(heading), np.sin(heading)])
    verts = np.vstack([np.zeros(2), np.cumsum(side * dirs, axis=0)])
    pts = [verts[0]]
    for k in range(1, len(verts) - 1):
        a = verts[k] - zone * dirs[k - 1]
        b = verts[k] + zone * dirs[k]
        prev = pts[-1]
        for u in np.linspace(0, 1, 20, endpoint=False)[1:]:
            pts.append(prev + u * (a - prev))
        for u in np.linspace(0, 1, 7):
            pts.append((1 - u) ** 2 * a + 2 * u * (1 - u) * verts[k] + u**2 * b)
    pts.append(verts[-1])
    pts = np.array(pts)
    corners = verts[1:-1]
    all_pts = np.vstack([np.column_stack([pts, np.full(len(pts), 0.8 * k)])
                         for k in range(layers)])
    n = len(all_pts)
    return Toolpath(all_pts, np.tile([0.0, 0.0, -1.0], (n, 1)), np.full(n, 30.0),
                    np.ones(n, np.int8), np.repeat(np.arange(layers), len(pts)),
                    np.ones(n, bool), np.full(n, zone)), corners


def test_corner_dwell_finds_the_150_degree_corners_only():
    angles = [150.0, 90.0, 150.0, 120.0, 60.0, 90.0]
    tp, corners = _polygon_path(angles)
    idx = find_corners(tp, 150.0)
    assert len(idx) == 4  # two per layer
    per_layer = len(tp) // 2
    found = tp.position_O[idx, :2]
    for c, f in zip(np.vstack([corners[[0, 2]]] * 2), found, strict=True):
        assert np.linalg.norm(c - f) < 1.0  # at the rounded apex
    assert np.all(tp.layer[idx] == [0, 0, 1, 1])
    s = FaultSchedule((FaultConfig(kind="corner_dwell", corner_angle_deg=150.0,
                                   extra_dwell_s=0.4, layers=(1, 1)),), toolpath=tp)
    dwell = s.corner_dwell_s()
    assert dwell.sum() == pytest.approx(0.8) and np.all(dwell[:per_layer] == 0)
    assert len(find_corners(tp, 120.0)) == 2 and len(find_corners(tp, 60.0)) == 2


def test_perturbed_calibration_moves_only_listed_sensors():
    T = {s: from_euler_deg([100.0 * k, 50.0, 900.0], [10.0 * k, 40.0, 0.0])
         for k, s in enumerate(("S1", "S2", "S3"))}
    cal = Calibration(T_B_S=T, T_F_O=np.eye(4), T_B_N=np.eye(4))
    pert = CalibrationPerturbation(translation_mm=(0.5, 0.0, -1.0), rotation_deg=(0.0, 0.0, 2.0),
                                   sensors=("S2",))
    out = perturbed_calibration(cal, pert)
    assert np.array_equal(out.T_B_S["S1"], T["S1"]) and np.array_equal(out.T_B_S["S3"], T["S3"])
    err = invert(T["S2"]) @ out.T_B_S["S2"]
    np.testing.assert_allclose(err[:3, 3], [0.5, 0.0, -1.0], atol=1e-12)
    assert math.degrees(math.acos((np.trace(err[:3, :3]) - 1) / 2)) == pytest.approx(2.0)
    assert perturbed_calibration(cal, None) is cal
    with pytest.raises(ValueError, match="S4"):
        perturbed_calibration(cal, CalibrationPerturbation.model_construct(
            translation_mm=(0, 0, 0), rotation_deg=(0, 0, 0), sensors=("S4",)))


@pytest.mark.parametrize("layers, message", [
    ((40, 50), r"faults\[0\]\.layers: \[40, 50\] starts beyond the part's last layer 4"),
    ((-2, 1), r"faults\[0\]\.layers: \[-2, 1\] starts below layer 0"),
])
def test_fault_windows_outside_the_part_are_refused(layers, message):
    from types import SimpleNamespace

    five_layers = SimpleNamespace(layer=np.repeat(np.arange(5), 10))
    bump = FaultConfig(kind="bump", layers=layers, center_O_mm=(20.0, 20.0), height_mm=0.5,
                       width_mm=6.0)
    with pytest.raises(ValueError, match=message):
        FaultSchedule([bump], toolpath=five_layers)
    FaultSchedule([bump.model_copy(update={"layers": (2, 9)})], toolpath=five_layers)


def test_scenario_with_a_fault_beyond_the_part_exits_2_naming_the_window(tmp_path):
    from typer.testing import CliRunner

    from dm2.cli.main import app

    path = tmp_path / "far.toml"
    path.write_text('schema = 1\nname = "far"\n[part]\ngenerator = "pad"\n'
                    '[part.params]\nwidth_mm = 20.0\ndepth_mm = 10.0\nheight_mm = 2.4\n'
                    '[[faults]]\nkind = "bump"\nlayers = [40, 50]\n'
                    'center_O_mm = [60.0, 60.0]\nheight_mm = 0.5\nwidth_mm = 6.0\n',
                    encoding="utf-8")
    res = CliRunner().invoke(app, ["run", str(path), "--out", str(tmp_path / "run")])
    assert res.exit_code == 2
    assert "faults[0].layers: [40, 50] starts beyond" in res.output
    assert not (tmp_path / "run").exists()
