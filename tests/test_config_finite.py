"""Every float in every configuration is finite and physically bounded (issue 57, item 6):
refused with exit 2 and one line naming the file, the key and the value, no traceback."""

from __future__ import annotations

import json

import pytest
from test_monitor_cli import _record
from test_monitor_scene import Scene, make_calibration, raster_run
from typer.testing import CliRunner

from dm2.cli.main import app

PAD = 'schema = 1\nname = "pad"\nseed = 1\n[part]\ngenerator = "pad"\n' \
      'params = { width_mm = 20.0, depth_mm = 10.0, height_mm = 4.0 }\n'
BUMP = '[[faults]]\nkind = "bump"\nlayers = [1, 2]\ncenter_O_mm = [60.0, 60.0]\n' \
       'width_mm = 4.0\nheight_mm = {h}\n'


def _refused(res, path, key, value):
    """Exit 2, no exception, and one line naming file, key and value."""
    assert res.exit_code == 2, res.output
    assert res.exception is None or isinstance(res.exception, SystemExit), res.exception
    assert "Traceback" not in res.output
    lines = [ln for ln in res.output.splitlines() if key in ln]
    assert lines, res.output
    assert str(path) in lines[0] and value in lines[0], lines[0]


@pytest.mark.parametrize("command", ["run", "simulate"])
@pytest.mark.parametrize("table, key, value, shown", [
    ("noise", "range_sigma_mm", "inf", "inf"),
    ("noise", "range_sigma_mm", "1e308", "1e+308"),
    ("noise", "range_sigma_mm", "nan", "nan"),
    ("process", "plume_sigma_mm", "1e308", "1e+308"),
    ("process", "plume_sigma_mm", "inf", "inf"),
    ("process", "feed_g_min", "inf", "inf"),
    ("process", "feed_g_min", "1e12", "1000000000000.0"),
    ("twin_process", "feed_g_min", "-inf", "-inf"),
])
def test_scenario_values_not_finite_or_absurd_are_refused(tmp_path, command, table, key,
                                                          value, shown):
    path = tmp_path / "bad.toml"
    path.write_text(PAD + f"[{table}]\n{key} = {value}\n")
    out = tmp_path / ("out" if command == "run" else "out.mcap")
    res = CliRunner().invoke(app, [command, str(path), "--out", str(out)])
    _refused(res, path, f"{table}.{key}", shown)
    assert not out.exists()


@pytest.mark.parametrize("height, shown", [("1e308", "1e+308"), ("inf", "inf"),
                                           ("60.0", "60.0")])
def test_fault_height_beyond_50_mm_is_refused_before_the_twin_runs(tmp_path, height, shown):
    """1e308 crashed the reconstruction check (exit 139) and passed `dm2 simulate`."""
    path = tmp_path / "bump.toml"
    path.write_text(PAD + BUMP.format(h=height))
    for command, out in (("simulate", tmp_path / "x.mcap"), ("run", tmp_path / "run")):
        res = CliRunner().invoke(app, [command, str(path), "--out", str(out)])
        _refused(res, path, "faults.0.height_mm", shown)
        assert not out.exists()


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    cal = make_calibration()
    msgs, _ = raster_run(Scene(), cal, [((40, 58, 0), (80, 58, 0))], step_mm=3.0,
                         noise_mm=0.05, seed=5, t0_s=1.0)
    path = tmp_path_factory.mktemp("rec") / "in.mcap"
    _record(path, msgs, cal, attach=True)
    return path


@pytest.mark.parametrize("text, key, shown", [
    ("[process]\nplume_sigma_mm = inf\n", "process.plume_sigma_mm", "inf"),
    ("[process]\nplume_sigma_mm = 1e308\n", "process.plume_sigma_mm", "1e+308"),
    ("[monitor]\ndelta_global_mm = nan\n", "monitor.delta_global_mm", "nan"),
    ("[monitor.gates]\nmax_tcp_speed_mm_s = inf\n", "monitor.gates.max_tcp_speed_mm_s", "inf"),
    ("[monitor.uncertainty]\nfloor_mm = inf\n", "monitor.uncertainty", "inf"),
])
def test_config_file_values_not_finite_are_refused(tmp_path, recording, text, key, shown):
    """`[process] plume_sigma_mm = inf` in a --config gave 0 tracks and exit 0."""
    config = tmp_path / "cfg.toml"
    config.write_text(text)
    out = tmp_path / "out"
    res = CliRunner().invoke(app, ["monitor", str(recording), "--out", str(out),
                                   "--config", str(config)])
    _refused(res, config, key, shown)
    assert not out.exists()


def test_dm2_run_fails_a_run_that_fused_nothing(tmp_path):
    """`dm2 run` judges its run as `dm2 monitor` does: a twin whose profilers return nothing
    (every point dropped out) fused no profile, which is exit 1 and said so, not 'no defect'."""
    path = tmp_path / "blind.toml"
    path.write_text(PAD + "[noise]\ndropout_prob = 1.0\n")
    out = tmp_path / "run"
    res = CliRunner().invoke(app, ["run", str(path), "--out", str(out), "--duration", "4",
                                   "--no-record"])
    assert res.exit_code == 1, res.output
    text = " ".join(res.output.split())
    assert "pad: the run fused no profile" in text
    report = json.loads((out / "report.json").read_text())
    assert report["tracks"] == []
