"""``dm2 toolpath``: outputs on success; clear errors, exit 2 and nothing written on bad input."""

import numpy as np
import pytest
import trimesh
from typer.testing import CliRunner

from dm2.cli.main import app
from dm2.core.config import PartConfig, load_scenario
from dm2.toolpath import generate_toolpath
from dm2.toolpath.formats import read_csv
from scenarios import resolve_scenario
from scenarios.parts import build_part

runner = CliRunner()


def _run(args):
    return runner.invoke(app, ["toolpath", *args])


def test_pad_scenario_writes_csv_rapid_and_plot(tmp_path):
    out, mod, png = tmp_path / "tp.csv", tmp_path / "tp.mod", tmp_path / "tp.png"
    res = _run(["pad", "--out", str(out), "--rapid", str(mod), "--plot", str(png)])
    assert res.exit_code == 0, res.output
    sc = load_scenario(resolve_scenario("pad"))
    expected = generate_toolpath(build_part(sc.part, sc.cell.plate_size_mm), sc.toolpath)
    got = read_csv(out)
    assert np.array_equal(got.position_O, expected.position_O)
    assert got.n_layers == 5
    assert mod.read_text().count("MoveL") == len(expected)
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["tp.csv", "tp.mod", "tp.png"]


def test_stl_input(tmp_path):
    stl = tmp_path / "part.stl"
    trimesh.creation.box(extents=(20, 10, 4)).export(stl)
    res = _run([str(stl), "--out", str(tmp_path / "tp.csv")])
    assert res.exit_code == 0, res.output
    assert read_csv(tmp_path / "tp.csv").n_layers == 5


def _scenario(tmp_path, body):
    path = tmp_path / "bad.toml"
    path.write_text('schema = 1\nname = "bad"\n[part]\ngenerator = "pad"\n' + body)
    return path


@pytest.mark.parametrize("case, needle", [
    ("open_stl", "not watertight"),
    ("empty_stl", "empty"),
    ("zero_layer", "toolpath.layer_mm"),
    ("negative_layer", "toolpath.layer_mm"),
    ("unknown_key", "toolpath.layer_thickness"),
    ("wrong_type", "toolpath.line_spacing_mm"),
    ("unknown_param", "part.params.bogus_mm"),
    ("missing_scenario", "no_such_scenario"),
])
def test_bad_input_exits_2_and_writes_nothing(tmp_path, case, needle):
    inputs = tmp_path / "in"
    inputs.mkdir()
    outdir = tmp_path / "out"
    outdir.mkdir()
    if case == "open_stl":
        m = trimesh.creation.box(extents=(20, 10, 4))
        m.update_faces(np.arange(len(m.faces)) != 0)
        src = inputs / "open.stl"
        m.export(src)
    elif case == "empty_stl":
        src = inputs / "empty.stl"
        src.write_bytes(b"")
    elif case == "missing_scenario":
        src = "no_such_scenario"
    else:
        body = {"zero_layer": "[toolpath]\nlayer_mm = 0.0\n",
                "negative_layer": "[toolpath]\nlayer_mm = -0.8\n",
                "unknown_key": "[toolpath]\nlayer_thickness = 0.8\n",
                "wrong_type": '[toolpath]\nline_spacing_mm = "wide"\n',
                "unknown_param": "params = { bogus_mm = 3.0 }\n"}[case]
        src = _scenario(inputs, body)
    res = _run([str(src), "--out", str(outdir / "tp.csv"), "--rapid", str(outdir / "tp.mod"),
                "--plot", str(outdir / "tp.png")])
    assert res.exit_code == 2, res.output
    text = " ".join(res.output.split())
    assert needle in text
    if case not in ("missing_scenario",):
        assert str(src.name) in text
    assert list(outdir.iterdir()) == []


def test_build_part_errors_name_the_field():
    from dm2.core.config import ConfigError
    with pytest.raises(ConfigError, match="part.params.wall_mm"):
        build_part(PartConfig(generator="seven_sided", params={"wall_mm": 40.0}), (120, 120, 6))


def test_files_dm2_wrote_are_replaced_a_users_only_with_force(tmp_path):
    out, mod, png = tmp_path / "tp.csv", tmp_path / "tp.mod", tmp_path / "tp.png"
    args = ["pad", "--out", str(out), "--rapid", str(mod), "--plot", str(png)]
    assert _run(args).exit_code == 0
    assert _run(args).exit_code == 0  # its own files: replaced
    mine = tmp_path / "notes.csv"
    mine.write_text("a user's table\n")
    res = _run(["pad", "--out", str(mine)])
    assert res.exit_code == 2 and "not written by dm2" in res.output and "--force" in res.output
    assert mine.read_text() == "a user's table\n"
    assert _run(["pad", "--out", str(mine), "--force"]).exit_code == 0
    assert read_csv(mine).n_layers == 5
