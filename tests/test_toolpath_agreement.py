"""A toolpath is checked against the robot's motion over the whole run (issue: a toolpath
scaled 10x passed, because only the median of the first 500 robot states was compared)."""

from __future__ import annotations

import numpy as np
import pytest
from test_monitor_cli import _record
from test_monitor_scene import Scene, make_calibration, raster_run
from typer.testing import CliRunner

from dm2.cli.main import app
from dm2.core.messages import Toolpath
from dm2.fusion.path_agreement import first_departure
from dm2.toolpath.formats import write_csv

SCENE = Scene(boxes=[((50, 50, 0), (66, 66, 6))])
LINES = [((40, 58, 0), (80, 58, 0)), ((80, 64, 0), (40, 64, 0))]  # layer 0, then layer 1


def _toolpath(lines, layers=(0, 1)) -> Toolpath:
    pos = np.array([p for a, b in lines for p in (a, b)], float)
    n = len(pos)
    return Toolpath(position_O=pos, axis_O=np.tile([0.0, 0.0, -1.0], (n, 1)),
                    speed_mm_s=np.full(n, 15.0), kind=np.zeros(n, np.int8),
                    layer=np.repeat(np.asarray(layers), 2), spray_on=np.ones(n, bool),
                    zone_mm=np.zeros(n))


def _scaled(lines, f):
    c = np.mean([p for line in lines for p in line], axis=0)
    return [tuple(tuple(c + f * (np.asarray(p, float) - c)) for p in line) for line in lines]


def test_first_departure_names_the_window_and_layer_where_the_paths_part():
    t = np.arange(0.0, 8.0, 0.004)  # 250 Hz: 2000 states, the first 500 on layer 0
    x = np.interp(t, [0, 4, 4.0001, 8], [40, 80, 80, 40])
    y = np.where(t < 4, 58.0, 64.0)
    spots = np.column_stack([x, y, np.zeros_like(t)])
    assert first_departure(t, spots, _toolpath(LINES)) is None
    moved = _toolpath([LINES[0], ((80, 70, 0), (40, 70, 0))])  # layer 1 6 mm off
    part = first_departure(t, spots, moved)
    assert (part.start_s, part.layer) == (pytest.approx(4.0), 1)
    # 6 mm from the moved line, nearer the move that joins the layers at its start
    assert 3.0 < part.median_mm <= 6.0
    assert part.windows == 5  # four windows on layer 0 agreed first
    marked = first_departure(t, spots, moved, marks=[(0.0, 0), (3.99, 7)])
    assert (marked.layer, marked.layer_source) == (7, "layer marks")  # the recording's own
    still = np.tile(spots[:1] + [0, 30, 0], (len(t), 1))  # standing still far off: not judged
    assert first_departure(t, still, moved) is None


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    cal = make_calibration()
    msgs, _ = raster_run(SCENE, cal, LINES, step_mm=1.5, noise_mm=0.05, seed=11, t0_s=1.0)
    path = tmp_path_factory.mktemp("tp") / "run.mcap"
    _record(path, msgs, cal, attach=True)
    return path


@pytest.mark.parametrize(("name", "lines", "when", "layer"), [
    ("scaled10.csv", _scaled(LINES, 10.0), "0.9 s", 0),
    ("second_layer_off.csv", [LINES[0], ((80, 68, 0), (40, 68, 0))], "3.9 s", 1),
])
def test_monitor_refuses_a_toolpath_the_robot_did_not_follow(tmp_path, recording, name, lines,
                                                             when, layer):
    write_csv(_toolpath(lines), tmp_path / name)
    out = tmp_path / "out"
    res = CliRunner().invoke(app, ["monitor", str(recording), "--out", str(out),
                                   "--toolpath", str(tmp_path / name)])
    assert res.exit_code == 2, res.output
    text = "".join(res.output.split())  # the console wraps long paths
    assert f"{tmp_path / name}doesnotmatchtherecording" in text, text
    where = f"they part at {when} (layer {layer}, the nearest toolpath layer)"
    assert "".join(where.split()) in text, text
    assert "Traceback" not in res.output and not out.exists()


def test_monitor_accepts_the_toolpath_the_robot_followed(tmp_path, recording):
    write_csv(_toolpath(LINES), tmp_path / "right.csv")
    res = CliRunner().invoke(app, ["monitor", str(recording), "--out", str(tmp_path / "out"),
                                   "--toolpath", str(tmp_path / "right.csv"), "--no-analyse"])
    assert res.exit_code == 0, res.output
