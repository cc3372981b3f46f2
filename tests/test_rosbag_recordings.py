"""``dm2 monitor`` on rosbag2 recordings written by ``rosbags`` (not the project's writer): a dome
on a plate scanned by three line profilers with known poses (:mod:`rosbag_cell`).

The reconstruction is checked against the analytic surface: RMS distance of the mesh vertices
to the dome <= 0.25 mm, and >= 95 % of the area the fans swept (1 mm cells holding a true hit,
from the true poses) covered by the mesh.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from rosbag_cell import (
    DOME,
    FOREIGN_MAP,
    FOREIGN_SENSORS,
    dome_stream,
    storage_file,
    write_bag,
    write_mcap_ros2,
)
from typer.testing import CliRunner

from dm2.cli.main import app
from dm2.fusion.surface import read_ply
from dm2.toolpath.formats import write_rapid


@pytest.fixture(scope="module")
def cell():
    return dome_stream()


@pytest.fixture(scope="module")
def bags(tmp_path_factory, cell):
    """The two recordings, each as an MCAP bag and as a .db3 bag."""
    cal, msgs, _ = cell
    root = tmp_path_factory.mktemp("bags")
    (root / "map.toml").write_text(FOREIGN_MAP)
    return {
        "own_mcap": write_bag(root / "own_mcap", cal, msgs, duplicate=4),
        "own_db3": write_bag(root / "own_db3", cal, msgs, storage="sqlite3"),
        "foreign_split": write_bag(root / "foreign_split", cal, msgs, foreign=True,
                                   float64=True, split=True),
        "foreign_db3": write_bag(root / "foreign_db3", cal, msgs, foreign=True, float64=True,
                                 storage="sqlite3"),
        "map": root / "map.toml",
    }


def _monitor(tmp_path, *args):
    out = tmp_path / "out"
    res = CliRunner().invoke(app, ["monitor", *map(str, args), "--out", str(out),
                                   "--no-analyse"])
    return res, out


def _surface_check(out, hits):
    summary = json.loads((out / "monitor.json").read_text())
    surf = read_ply(out / "layer_0000.ply")
    rms = float(np.sqrt(np.mean(DOME.sdf(surf.vertices_O) ** 2)))
    cells = {tuple(c) for c in np.floor(hits[:, :2]).astype(int).tolist()}
    got = {tuple(c) for c in np.floor(surf.vertices_O[:, :2]).astype(int).tolist()}
    return summary, surf, rms, len(cells & got) / len(cells)


def test_sequence0_mcap_in_the_pipelines_names(tmp_path, cell, bags):
    """rosbag2's MCAP storage writes sequence 0 for every message: profiles are de-duplicated
    by (sensor, stamp) (the 4 profiles recorded twice), none is taken for a duplicate counter."""
    _cal, msgs, hits = cell
    res, out = _monitor(tmp_path, storage_file(bags["own_mcap"]))
    assert res.exit_code == 0, res.output
    summary, _surf, rms, coverage = _surface_check(out, hits)
    assert summary["dropped"] == {"duplicate_stamp": 4}
    n_profiles = sum(type(m).__name__ == "Profile" for m in msgs)
    assert summary["profiles_fused"] == n_profiles
    assert rms <= 0.25 and coverage >= 0.95, (rms, coverage)


def test_mcap_ros2_support_file_with_sequence_0(tmp_path, cell):
    """The measured case: one MCAP file in the pipeline's names from mcap-ros2-support, every
    sequence 0 (it lost 621 of 624 profiles as duplicate counters and covered 1.9 %)."""
    cal, msgs, hits = cell
    res, out = _monitor(tmp_path, write_mcap_ros2(tmp_path / "m.mcap", cal, msgs))
    assert res.exit_code == 0, res.output
    summary, _surf, rms, coverage = _surface_check(out, hits)
    assert summary["dropped"] == {}
    assert rms <= 0.25 and coverage >= 0.95, (rms, coverage)


def test_foreign_names_six_link_chain_float64_split_bag(tmp_path, cell, bags):
    _cal, msgs, hits = cell
    res, out = _monitor(tmp_path, bags["foreign_split"], "--map", bags["map"])
    assert res.exit_code == 0, res.output
    summary, _surf, rms, coverage = _surface_check(out, hits)
    assert summary["dropped"] == {} and summary["recording_skipped"] == {}
    assert summary["profiles_fused"] == sum(type(m).__name__ == "Profile" for m in msgs)
    assert rms <= 0.25 and coverage >= 0.95, (rms, coverage)


@pytest.mark.parametrize(("mcap", "db3", "args"), [
    ("own_mcap", "own_db3", ()), ("foreign_split", "foreign_db3", ("--map",))])
def test_db3_bag_gives_the_same_surface(tmp_path, bags, mcap, db3, args):
    extra = [a for a in args for a in (a, bags["map"])]
    res_a, out_a = _monitor(tmp_path / "a", bags[mcap], *extra)
    res_b, out_b = _monitor(tmp_path / "b", storage_file(bags[db3]), *extra)
    assert res_a.exit_code == 0 and res_b.exit_code == 0, res_a.output + res_b.output
    sa, sb = read_ply(out_a / "layer_0000.ply"), read_ply(out_b / "layer_0000.ply")
    assert sa.n_vertices == sb.n_vertices
    np.testing.assert_allclose(sa.vertices_O, sb.vertices_O, atol=1e-9)


@pytest.mark.parametrize(("old", "new", "key", "offers"), [
    ('S2 = "/scanners/rear/points"', 'S2 = "/scanners/back/points"', "topics.profiles.S2",
     "/scanners/rear/points (sensor_msgs/msg/PointCloud2)"),
    ('flange = "tool0"', 'flange = "tool_0"', "frames.flange", "link_6, nozzle_exit"),
    ('S3 = "scanner_right"', 'S3 = "scanner_r"', "frames.sensors.S3", "scanner_right"),
    ('[frames]', '[frames]\nbasis = "x"', "frames.basis", "allowed: base, flange"),
])
def test_bad_map_exits_2_naming_the_key_and_writes_nothing(tmp_path, bags, old, new, key,
                                                            offers):
    bad = tmp_path / "bad.toml"
    bad.write_text(FOREIGN_MAP.replace(old, new))
    res, out = _monitor(tmp_path, bags["foreign_split"], "--map", bad)
    assert res.exit_code == 2, res.output
    text = " ".join(res.output.split())
    assert key in text and offers in text, text
    assert not out.exists()


def test_sensor_on_a_moving_frame_is_refused(tmp_path, cell):
    """The tf tree hangs S1 off link_6: it would move with the robot, contradicting a cell
    where the robot moves the substrate."""
    cal, msgs, _ = cell
    bag = write_bag(tmp_path / "moving", cal, msgs[:400], foreign=True)
    rosmap = tmp_path / "map.toml"
    rosmap.write_text(FOREIGN_MAP.replace('S1 = "scanner_left"', 'S1 = "link_6"'))
    res, out = _monitor(tmp_path, bag, "--map", rosmap)
    assert res.exit_code == 2
    text = " ".join(res.output.split())
    assert "frames.sensors.S1 = 'link_6' moves relative to frames.base" in text
    assert "link_5 -> link_6" in text and not out.exists()


def test_clouds_in_the_wrong_frame_are_off_plane_and_named(tmp_path, cell):
    """S1's clouds are published in scanner_rear's frame: in S1's plane they lie off it."""
    cal, msgs, _ = cell
    frames = {**FOREIGN_SENSORS, "S1": "scanner_rear"}
    bag = write_bag(tmp_path / "wrong", cal, msgs[:600], foreign=True, cloud_frames=frames)
    rosmap = tmp_path / "map.toml"
    rosmap.write_text(FOREIGN_MAP)
    res, out = _monitor(tmp_path, bag, "--map", rosmap)
    assert res.exit_code == 0, res.output
    summary = json.loads((out / "monitor.json").read_text())
    (problem,) = summary["recording_problems"]
    n_off = summary["recording_skipped"]["off_plane_points"]
    assert problem.startswith(f"/scanners/left/points: {n_off} of its ")
    assert "frames.sensors.S1 = 'scanner_left'" in problem


def test_toolpath_as_rapid_module_splits_layers(tmp_path, cell, bags):
    from dm2.core.messages import Toolpath

    lines = [((30.0, 48.0), (90.0, 48.0)), ((90.0, 60.0), (30.0, 60.0)),
             ((30.0, 72.0), (90.0, 72.0))]
    pos = np.array([[x, y, 0.0] for a, b in lines for x, y in (a, b)])
    n = len(pos)
    tp = Toolpath(position_O=pos, axis_O=np.tile([0.0, 0.0, -1.0], (n, 1)),
                  speed_mm_s=np.full(n, 15.0), kind=np.zeros(n, np.int8),
                  layer=np.array([0, 0, 1, 1, 1, 1]), spray_on=np.ones(n, bool),
                  zone_mm=np.zeros(n))
    write_rapid(tp, tmp_path / "path.mod")
    res, out = _monitor(tmp_path, bags["foreign_split"], "--map", bags["map"], "--toolpath",
                        tmp_path / "path.mod")
    assert res.exit_code == 0, res.output
    summary = json.loads((out / "monitor.json").read_text())
    assert summary["layer_source"] == "toolpath"
    assert [row["layer"] for row in summary["layers"]] == [0, 1]


def test_own_recording_of_profiles_without_counters_dedupes_by_stamp(tmp_path, cell):
    """The project's writer given counter-less profiles writes sequence 0; reading it back
    recognises the missing counters instead of taking every profile for a duplicate."""
    from dm2.core.messages import Profile
    from dm2.io.bag_recording import open_recording
    from dm2.io.recording_writer import RecordingWriter

    cal, msgs, _ = cell
    part = msgs[:800]
    with RecordingWriter(tmp_path / "r.mcap") as w:
        w.write_static_tf(cal)
        for m in part:
            if isinstance(m, Profile):
                m = Profile(m.sensor_id, m.stamp_s, None, m.xz_S, m.valid, m.intensity)
            w.write(m)
    rec = open_recording(tmp_path / "r.mcap")
    assert type(rec).__name__ == "Recording" and not rec.has_counters
    profiles = [m for m in rec.messages() if isinstance(m, Profile)]
    assert len(profiles) == sum(isinstance(m, Profile) for m in part)
    assert {p.counter for p in profiles} == {None}


def test_layer_marks_on_the_mapped_layer_topic(tmp_path, cell):
    cal, msgs, _ = cell
    t_mid = msgs[len(msgs) // 2].stamp_s
    bag = write_bag(tmp_path / "marks", cal, msgs, foreign=True,
                    marks=[(msgs[0].stamp_s, 0), (t_mid, 1)])
    rosmap = tmp_path / "map.toml"
    rosmap.write_text(FOREIGN_MAP.replace('[frames]', 'layer = "/dm2/layer"\n[frames]'))
    res, out = _monitor(tmp_path, bag, "--map", rosmap)
    assert res.exit_code == 0, res.output
    summary = json.loads((out / "monitor.json").read_text())
    assert summary["layer_source"] == "marks"
    assert [row["layer"] for row in summary["layers"]] == [0, 1]
    assert summary["layers"][0]["stamp_s"] <= t_mid


def test_profiles_in_a_tf_hole_are_dropped_and_counted(tmp_path, cell):
    """/tf stalls for 0.3 s (> max_pose_gap_s = 0.05 s): no two samples within the gap
    bracket a profile in the hole, so every one there is dropped, counted, and not fused."""
    from dm2.core.messages import Profile

    cal, msgs, _ = cell
    part = msgs[:1500]
    t0 = part[600].stamp_s
    hole = (t0, t0 + 0.3)
    bag = write_bag(tmp_path / "hole", cal, part, foreign=True, tf_hole_s=hole)
    rosmap = tmp_path / "map.toml"
    rosmap.write_text(FOREIGN_MAP)
    res, out = _monitor(tmp_path, bag, "--map", rosmap)
    assert res.exit_code == 0, res.output
    summary = json.loads((out / "monitor.json").read_text())
    states = [m.stamp_s for m in part if type(m).__name__ == "RobotState"]
    before = max(t for t in states if t <= hole[0])
    after = min(t for t in states if t >= hole[1])
    lost = [m for m in part if isinstance(m, Profile) and before < m.stamp_s < after]
    n = sum(isinstance(m, Profile) for m in part)
    assert len(lost) > 10
    assert summary["recording_skipped"] == {"tf lookup beyond max_pose_gap_s": len(lost)}
    assert summary["profiles_fused"] == n - len(lost)
