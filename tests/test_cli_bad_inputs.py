"""Every command, every file it reads, every kind of wrong input: a non-zero exit with a
message, never a traceback (issue 57: every error in --map, --config, --toolpath and the cell
file is one line naming the file, exit 2).

The table below names each command's file slots; a command added to the app without a row
fails :func:`test_every_command_is_walked`.
"""

from __future__ import annotations

import inspect

import pytest
import typer
from test_monitor_cli import _record
from test_monitor_scene import Scene, make_calibration, raster_run
from typer.testing import CliRunner

from dm2.cli.main import app

PAD = ('schema = 1\nname = "pad"\nseed = 1\n[part]\ngenerator = "pad"\n'
       'params = { width_mm = 20.0, depth_mm = 10.0, height_mm = 4.0 }\n')
BAD = {
    "missing": None,  # a path that does not exist
    "folder": None,  # a folder where a file is expected
    "garbage": b"\x00\xff\xfe[[[ = = garbage \x89PNG\r\n",
    "empty": b"",
    "wrong_types": (
        b'schema = "one"\nname = 5\ncalibration = 7\ntoolpath = 3.5\n'
        b'plate_size_mm = ["a", 1, 2]\n[part]\ngenerator = 3\n[process]\nfeed_g_min = "fast"\n'
        b'[monitor]\nvoxel_mm = [1]\n[live]\negm = 5\nbridges = "x"\n[topics]\nlayer = 3\n'
        b'[frames]\nbase = 4\n[T_B_N]\ntranslation_mm = "x"\n[sensors.S1]\nquaternion_wxyz = 1\n'
        b'[artifact]\nspheres = 3\n'),
    "not_finite": (PAD + '[process]\nplume_sigma_mm = inf\nfeed_g_min = nan\n'
                   '[monitor]\nvoxel_mm = inf\n[noise]\nrange_sigma_mm = 1e308\n'
                   '[T_B_N]\ntranslation_mm = [inf, 0.0, 0.0]\n'
                   'quaternion_wxyz = [nan, 0.0, 0.0, 0.0]\n').encode(),
    "bad_csv": b"index,x_mm,y_mm,z_mm\n0,a,inf,\n1,2\n",
    "bad_csv_values": (b"index,x_mm,y_mm,z_mm,nx,ny,nz,speed_mm_s,kind,layer\n"
                       b"0,inf,0,0,0,0,1,30,infill,0\n1,nan,1,0,0,0,1,-5,nowhere,x\n"),
    "deep_csv": (b"index,x_mm,y_mm,z_mm,ax,ay,az,speed_mm_s,kind,layer,spray_on,zone_mm\n"
                 b"0,inf,0,0,0,0,1,30,infill,0,1,1\n1,nan,1,0,0,0,1,-5,nowhere,x,2,1e308\n"),
    "deep_calibration": (b"schema = 1\n[T_B_N]\ntranslation_mm = [inf, 0.0, 0.0]\n"
                         b"quaternion_wxyz = [0.0, 1.0, 0.0, 0.0]\n[T_F_O]\n"
                         b"translation_mm = [0.0, 0.0, nan]\nquaternion_wxyz = [1.0, 0.0, 0.0]\n"
                         b"[sensors.S1]\ntranslation_mm = [1e308, 0, 0]\n"
                         b'quaternion_wxyz = ["a", 0, 0, 0]\n'),
    "deep_map": b'[topics]\nlayer = 3\nrobot = ["x"]\n[frames]\nbase = 4.5\n',
    "bad_cell": (b'schema = 1\nname = "cell"\ncalibration = "no_such.toml"\n'
                 b'plate_size_mm = [120.0, 120.0, inf]\n[live]\negm = "nohost:99999"\n'
                 b'profiles = 7\ncontrollers = ["not an address"]\n'),
}


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    root = tmp_path_factory.mktemp("bad")
    paths = {"missing": root / "no_such_file.toml", "folder": root / "a_folder"}
    paths["folder"].mkdir()
    for name, data in BAD.items():
        if data is not None:
            paths[name] = root / f"{name}.toml"
            paths[name].write_bytes(data)
    cal = make_calibration()
    msgs, _ = raster_run(Scene(), cal, [((40, 58, 0), (80, 58, 0))], step_mm=3.0,
                         noise_mm=0.05, seed=5, t0_s=1.0)
    good = root / "good.mcap"
    _record(good, msgs, cal, attach=True)
    return root, paths, good


# command -> how to put a bad input in each of its slots ({bad}: the bad path, {good}: a valid
# recording, {out}: a new output path)
SLOTS = {
    "simulate": [["simulate", "{bad}", "--out", "{out}.mcap"]],
    "toolpath": [["toolpath", "{bad}", "--out", "{out}.csv"]],
    "monitor": [["monitor", "{bad}", "--out", "{out}"],
                ["monitor", "{good}", "--calibration", "{bad}", "--out", "{out}"],
                ["monitor", "{good}", "--toolpath", "{bad}", "--out", "{out}"],
                ["monitor", "{good}", "--map", "{bad}", "--out", "{out}"],
                ["monitor", "{good}", "--config", "{bad}", "--out", "{out}"],
                ["monitor", "--live", "{bad}", "--out", "{out}"]],
    "calibrate": [["calibrate", "{bad}", "--out", "{out}"],
                  ["calibrate", "{good}", "--artifact", "{bad}", "--out", "{out}"],
                  ["calibrate", "{good}", "--prior", "{bad}", "--out", "{out}"],
                  ["calibrate", "--rehearse", "{bad}", "--out", "{out}"]],
    "fit-efficiency": [["fit-efficiency", "{bad}", "--out", "{out}.toml"],
                       ["fit-efficiency", "{good}", "--calibration", "{bad}", "--out",
                        "{out}.toml"],
                       ["fit-efficiency", "{good}", "--toolpath", "{bad}", "--out", "{out}.toml"],
                       ["fit-efficiency", "{good}", "--map", "{bad}", "--out", "{out}.toml"],
                       ["fit-efficiency", "{good}", "--config", "{bad}", "--out", "{out}.toml"]],
    "run": [["run", "{bad}", "--out", "{out}"],
            ["run", "pad", "--calibration", "{bad}", "--out", "{out}"]],
    "serve-twin": [["serve-twin", "{bad}", "--wait-s", "0"]],
    "recover": [["recover", "{bad}", "--out", "{out}.mcap"]],
    "bench": [["bench", "--suite", "{bad}", "--out", "{out}"]],
    "sweep": [["sweep", "{bad}", "--out", "{out}"]],
    "view": [["view", "{bad}", "--port", "1"]],
    "report": [["report", "{bad}"]],
}


def _commands() -> set[str]:
    return set(typer.main.get_command(app).commands)


def test_every_command_is_walked():
    assert _commands() == set(SLOTS)


CASES = [(cmd, k, kind) for cmd, rows in SLOTS.items() for k in range(len(rows))
         for kind in BAD]


@pytest.mark.parametrize("command, row, kind", CASES,
                         ids=[f"{c}-{r}-{k}" for c, r, k in CASES])
def test_a_wrong_input_is_a_message_not_a_traceback(tmp_path, inputs, command, row, kind):
    root, paths, good = inputs
    args = [a.format(bad=paths[kind], good=good, out=tmp_path / "out")
            for a in SLOTS[command][row]]
    res = CliRunner().invoke(app, args)
    assert res.exit_code != 0, (args, res.output)
    assert res.exception is None or isinstance(res.exception, SystemExit), \
        (args, repr(res.exception))
    assert "Traceback" not in res.output, res.output
    errors = [ln for ln in res.output.splitlines() if ln.startswith("error:")]
    assert errors, (args, res.output)
    assert res.exit_code == 2, (args, res.exit_code, res.output)
    assert paths[kind].name in errors[0], (args, errors[0])  # the file is named
    assert not (tmp_path / "out").exists() or command == "calibrate"


# a valid invocation of each command, to which one number option is then added
VALID = {"simulate": ["pad"], "toolpath": ["pad", "--out", "{out}.csv"],
         "monitor": ["{good}", "--out", "{out}"], "calibrate": ["--rehearse"],
         "fit-efficiency": ["{good}", "--out", "{out}.toml"], "run": ["pad"],
         "serve-twin": ["pad"], "recover": ["{good}"], "bench": [], "sweep": ["pad"],
         "view": ["{out}"], "report": ["{out}"]}


def _number_options():
    """(command, option) for every float option, read from the commands' signatures."""
    out = []
    for name, cmd in sorted(typer.main.get_command(app).commands.items()):
        for p in inspect.signature(cmd.callback).parameters.values():
            decls = [d for d in getattr(p.default, "param_decls", None) or ()
                     if d.startswith("--")]
            if p.annotation in (float, "float") and decls:
                out.append((name, decls[0]))
    return out


@pytest.mark.parametrize("value", ["nan", "inf", "-inf"])
def test_a_number_option_that_is_not_finite_is_refused(tmp_path, inputs, value):
    """click reads ``nan`` and ``inf`` as floats (and ``nan`` passes its ranges): every float
    option of every command refuses them before any work, naming the option."""
    _, _, good = inputs
    assert set(VALID) == set(SLOTS)
    options = _number_options()
    assert len(options) >= 10
    for command, option in options:
        args = [a.format(good=good, out=tmp_path / "out") for a in VALID[command]]
        res = CliRunner().invoke(app, [command, *args, option, value])
        assert res.exit_code == 2, (command, option, res.output)
        assert res.exception is None or isinstance(res.exception, SystemExit), \
            (command, option, repr(res.exception))
        assert option in res.output, (command, option, res.output)
        assert not (tmp_path / "out").exists()
