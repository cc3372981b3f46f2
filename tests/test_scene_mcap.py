"""``scene.mcap``: a run in Foxglove's schemas, read back with the ``mcap`` library.

One short pad run with a 1 mm bump from layer 2 (as in tests/test_report_browser.py): every
channel is there with Foxglove's own schema, each channel's stamps are monotonic and on the
run's clock, the tracks and the findings are report.json's, the bump is found as an overbuild
track box at its place, the raw profiles lie on the plate where the part is, the frames chain
plate -> flange -> base with the nozzle and the three sensors. A user's scene.mcap is never
replaced; the shipped layout is the one the code builds.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from mcap.reader import make_reader
from typer.testing import CliRunner

from dm2.cli.main import app
from dm2.report.summary import verdict

BUMP = {"kind": "bump", "center_O_mm": [57.0, 60.0], "height_mm": 1.0, "width_mm": 5.0,
        "layers": [2, 2]}
CHANNELS = {"/dm2/surface": "foxglove.PointCloud", "/dm2/reference": "foxglove.PointCloud",
            "/dm2/profiles": "foxglove.PointCloud", "/dm2/tracks": "foxglove.SceneUpdate",
            "/dm2/alarm_markers": "foxglove.SceneUpdate", "/dm2/alarms": "foxglove.Log",
            "/dm2/findings": "foxglove.Log", "/tf": "foxglove.FrameTransforms",
            "/dm2/track_stats": "dm2.TrackStats"}


def bump_scenario(tmp: Path, duration_s: float = 30.0) -> Path:
    lines = [f'schema = 1\nname = "pad_bump"\nseed = 5\nduration_s = {duration_s}\n[part]\n'
             'generator = "pad"\n[toolpath]\ncontour_angle_deg = 0.0\n[process]\n'
             "feed_g_min = 26.0\n[[faults]]\n"]
    lines += [f"{k} = {json.dumps(v)}\n" for k, v in BUMP.items()]
    path = tmp / "pad_bump.toml"
    path.write_text("".join(lines))
    return path


def decoder(schema):
    """A function bytes -> protobuf message for an MCAP protobuf schema record."""
    fds = descriptor_pb2.FileDescriptorSet.FromString(schema.data)
    pool = descriptor_pool.DescriptorPool()
    for f in fds.file:
        pool.Add(f)
    cls = message_factory.GetMessageClass(pool.FindMessageTypeByName(schema.name))
    return cls.FromString


def read_scene(path: Path) -> dict:
    """topic -> {"schema", "encoding", "messages": [(log_time_ns, decoded)]}."""
    out = {}
    with open(path, "rb") as f:
        for schema, channel, message in make_reader(f).iter_messages(log_time_order=False):
            entry = out.setdefault(channel.topic, {"schema": schema.name, "messages": [],
                                                   "encoding": channel.message_encoding})
            if channel.message_encoding == "protobuf":
                decode = entry.setdefault("decode", decoder(schema))
                msg = decode(message.data)
            else:
                msg = json.loads(message.data)
            entry["messages"].append((message.log_time, msg))
    return out


def stamp_s(ts) -> float:
    return ts.seconds + ts.nanos * 1e-9


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("scene")
    res = CliRunner().invoke(app, ["run", str(bump_scenario(tmp)), "--out", str(tmp / "run")])
    assert res.exit_code == 0, res.output
    report = json.loads((tmp / "run" / "report.json").read_text())
    return tmp / "run", report, read_scene(tmp / "run" / "scene.mcap")


@pytest.fixture(scope="module")
def monitored(run):
    """``dm2 monitor`` of the run's own recording."""
    run_dir = run[0]
    out = run_dir.parent / "monitor"
    res = CliRunner().invoke(app, ["monitor", str(run_dir / "run.mcap"), "--out", str(out)])
    assert res.exit_code == 0, res.output
    report = json.loads((out / "report" / "report.json").read_text())
    return out, report, read_scene(out / "scene.mcap")


def test_every_channel_has_foxglove_schema_and_monotonic_run_stamps(run):
    run_dir, report, scene = run
    assert {t: e["schema"] for t, e in scene.items()} == CHANNELS
    for topic, e in scene.items():
        times = [t for t, _ in e["messages"]]
        assert times == sorted(times), topic
        assert e["encoding"] == ("json" if topic == "/dm2/track_stats" else "protobuf")
    manifest = json.loads((run_dir / ".dm2-manifest.json").read_text())
    assert "scene.mcap" in manifest["files"]
    # on the run's clock: one surface per layer at the layer's close, as report.json has it
    layers = report["layers"]
    surfaces = scene["/dm2/surface"]["messages"]
    assert len(surfaces) == len(layers)
    for (t_ns, cloud), layer in zip(surfaces, layers, strict=True):
        assert stamp_s(cloud.timestamp) == pytest.approx(t_ns * 1e-9, abs=1e-9)
        assert cloud.frame_id == "plate"
        assert {f.name for f in cloud.fields} >= {"x", "y", "z", "red", "green", "blue",
                                                  "alpha", "deviation_mm"}
        assert stamp_s(cloud.timestamp) == pytest.approx(layer["stamp_s"], abs=1e-6)
        assert len(cloud.data) // cloud.point_stride == layer["statistics"]["n_vertices"]


def test_tracks_and_findings_equal_the_report(run):
    _, report, scene = run
    seen = check_tracks_and_findings(report, scene)
    # the bump: an overbuild track from layer 2 whose box holds its centre (57, 60) mm
    (bump,) = [t for t in report["tracks"] if t["kind"] == "overbuild"]
    assert bump["first_layer"] == 2
    _, box = seen[(bump["id"], 2)]
    centre = box.cubes[0].pose.position
    size = box.cubes[0].size
    assert abs(centre.x * 1e3 - 57.0) <= size.x * 1e3 / 2 + 1.0
    assert abs(centre.y * 1e3 - 60.0) <= size.y * 1e3 / 2 + 1.0


def check_tracks_and_findings(report: dict, scene: dict, alarms: bool = True) -> dict:
    """The scene's track boxes, plot rows, alarms, verdict and findings are the report's;
    returns (track id, layer) -> (entity metadata, entity)."""
    seen = {}  # (track id, layer) -> entity metadata
    for _, update in scene["/dm2/tracks"]["messages"]:
        assert [d.type for d in update.deletions] == [1]  # ALL: a track lives where it is seen
        for e in update.entities:
            meta = {kv.key: kv.value for kv in e.metadata}
            seen[(int(meta["id"]), int(meta["layer"]))] = (meta, e)
    expected = {(t["id"], h["layer"]): (t, h) for t in report["tracks"] for h in t["history"]}
    assert set(seen) == set(expected)
    for key, (meta, entity) in seen.items():
        _, h = expected[key]
        assert meta["kind"] == h["kind"]
        assert float(meta["area_mm2"]) == pytest.approx(h["area_mm2"], rel=1e-5)
        assert float(meta["peak_mm"]) == pytest.approx(h["max_deviation_mm"], rel=1e-5)
        assert entity.id == f"track-{key[0]}" and entity.cubes and entity.texts
    stats = [m for _, m in scene["/dm2/track_stats"]["messages"]]
    assert {(s["track_id"], s["layer"]) for s in stats} == set(expected)
    logs = [m.message for _, m in scene["/dm2/findings"]["messages"]]
    v = verdict(report)
    assert logs[0] == f"verdict: {v['headline']}"
    assert logs[1:1 + len(v["sentences"])] == [f"verdict: {s}" for s in v["sentences"]]
    assert logs[1 + len(v["sentences"]):] == [f"process finding: {f}" for f in
                                              (report.get("process") or {}).get("findings", [])]
    if not alarms:
        return seen
    logged = scene.get("/dm2/alarms", {"messages": []})["messages"]
    for (_, log), a in zip(logged, report["realtime"]["alarms"], strict=True):
        assert stamp_s(log.timestamp) == pytest.approx(a["stamp_s"], abs=1e-9)
        assert a["kind"] in log.message
    return seen


def test_frames_and_raw_profiles_in_the_plate_frame(run):
    _, report, scene = run
    children = set()
    for _, tfs in scene["/tf"]["messages"]:
        children |= {(t.parent_frame_id, t.child_frame_id) for t in tfs.transforms}
    assert children == {("base", "flange"), ("flange", "plate"), ("base", "nozzle"),
                        ("base", "S1"), ("base", "S2"), ("base", "S3")}
    pts = []
    for _, cloud in scene["/dm2/profiles"]["messages"]:
        rec = np.frombuffer(cloud.data, dtype=np.dtype([("x", "<f4"), ("y", "<f4"),
                                                        ("z", "<f4"), ("rgba", "<u4"),
                                                        ("d", "<f4")]))
        pts.append(np.column_stack([rec["x"], rec["y"], rec["z"]]) * 1e3)
    pts = np.concatenate(pts)
    # the pad (20 x 10 mm at the plate's centre, 4 mm at most): registered profile points
    # that hit the part lie on it; the median point is on the part's footprint or the plate
    top = max(layer["stamp_s"] for layer in report["layers"])
    assert top > 0
    assert np.all(np.abs(np.median(pts[:, :2], axis=0) - [60.0, 60.0]) < 15.0)
    assert -0.5 < np.median(pts[:, 2]) < 4.5


def test_monitor_writes_the_scene_on_the_recordings_clock(run, monitored):
    """dm2 monitor's scene: the same channels, its tracks and findings its report's, and every
    raw profile and robot pose in it at the stamp of a message of the recording it read."""
    from dm2.core.messages import Profile, RobotState
    from dm2.io.recording import read_recording

    out, report, scene = monitored
    assert {t: e["schema"] for t, e in scene.items()} == CHANNELS
    assert "scene.mcap" in json.loads((out / ".dm2-manifest.json").read_text())["files"]
    check_tracks_and_findings(report, scene)
    test_frames_and_raw_profiles_in_the_plate_frame((out, report, scene))
    stamps = {"prof": set(), "pose": set()}
    for msg in read_recording(run[0] / "run.mcap").messages():
        if isinstance(msg, Profile):
            stamps["prof"].add(round(msg.stamp_s * 1e9))
        elif isinstance(msg, RobotState):
            stamps["pose"].add(round(msg.stamp_s * 1e9))
    profiles = [t for t, _ in scene["/dm2/profiles"]["messages"]]
    poses = [t for t, m in scene["/tf"]["messages"]
             if any(x.child_frame_id == "flange" for x in m.transforms)]
    assert profiles and all(t in stamps["prof"] for t in profiles)
    assert poses and all(t in stamps["pose"] for t in poses)


def test_a_users_scene_file_is_kept(tmp_path):
    from dm2.report.outdir import write_manifest
    from dm2.report.scene_mcap import add_scene_to_run

    write_manifest(tmp_path, ["report.json"], command="dm2 run")
    (tmp_path / "report.json").write_text("{}")
    (tmp_path / "scene.mcap").write_bytes(b"mine")
    assert add_scene_to_run(tmp_path, []) is None
    assert (tmp_path / "scene.mcap").read_bytes() == b"mine"
    assert "scene.mcap" not in json.loads((tmp_path / ".dm2-manifest.json").read_text())["files"]


def test_the_shipped_layout_is_current():
    from dm2.report.scene_layout import LAYOUT_PATH, layout_json

    assert LAYOUT_PATH.read_text(encoding="utf-8") == layout_json()
    panels = json.dumps(json.loads(layout_json()))
    for needle in ('"panelType": "ThreeDee"', '"panelType": "Plot"', '"panelType": "Log"',
                   "/dm2/track_stats.area_mm2", "/dm2/track_stats.height_mm", "/dm2/alarms",
                   "/dm2/findings"):
        assert needle in panels, needle
