"""A `--map` that names a topic of the wrong message type is refused in one line (it crashed
with a TypeError traceback when `layer` named a PointCloud2 topic)."""

from __future__ import annotations

import pytest
from rosbag_cell import FOREIGN_MAP, dome_stream, write_bag
from typer.testing import CliRunner

from dm2.cli.main import app


@pytest.fixture(scope="module")
def bag(tmp_path_factory):
    cal, msgs, _ = dome_stream()
    return write_bag(tmp_path_factory.mktemp("bag") / "cell", cal, msgs[:400], foreign=True)


@pytest.mark.parametrize(("line", "key", "topic", "kind", "expected"), [
    ('layer = "/scanners/rear/points"', "topics.layer", "/scanners/rear/points",
     "sensor_msgs/msg/PointCloud2", "dm2_msgs/msg/LayerMark or std_msgs/msg/Int32"),
    ('joint_states = "/tf"', "topics.joint_states", "/tf", "tf2_msgs/msg/TFMessage",
     "sensor_msgs/msg/JointState"),
])
def test_a_mapped_topic_of_the_wrong_type_exits_2_in_one_line(tmp_path, bag, line, key, topic,
                                                              kind, expected):
    rosmap = tmp_path / "map.toml"
    text = FOREIGN_MAP.replace('joint_states = "/joint_states"\n', "")
    rosmap.write_text(text.replace("[frames]", f"{line}\n[frames]"))
    out = tmp_path / "out"
    res = CliRunner().invoke(app, ["monitor", str(bag), "--map", str(rosmap), "--out",
                                   str(out)])
    assert res.exit_code == 2, res.output
    assert "Traceback" not in res.output and res.exception is None or \
        isinstance(res.exception, SystemExit)
    text = " ".join(res.output.split())
    assert (f"--map {rosmap}: {key} = {topic!r} is a {kind}, not a {expected}") in text, text
    assert not out.exists()
