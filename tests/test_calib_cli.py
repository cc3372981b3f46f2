"""dm2 calibrate: rehearsal outputs, recorded runs, and clear exit-2 errors."""

from __future__ import annotations

import json

import numpy as np
from typer.testing import CliRunner

from dm2.cli.main import app
from dm2.core.calibration_io import read_calibration_provenance, read_calibration_toml
from dm2.core.config import load_scenario
from dm2.core.frames import apply, from_rotvec, pose_error
from dm2.core.messages import Calibration, Profile, RobotState
from dm2.io.recording import read_recording
from dm2.io.recording_writer import RecordingWriter
from scenarios import resolve_scenario
from twin.cell.cell import CellModel

runner = CliRunner()


def test_rehearsal_writes_errors_and_a_calibration_file_with_provenance(tmp_path):
    out = tmp_path / "cal"
    r = runner.invoke(app, ["calibrate", "--rehearse", "pad", "--poses", "12",
                            "--noise-mm", "0", "--robot-noise-mm", "0", "--seed", "2",
                            "--nozzle-error-mm", "0.8", "--holdout", "0", "--out", str(out)])
    assert r.exit_code == 0, r.output
    summary = json.loads((out / "rehearsal.json").read_text())
    assert set(summary["sensors"]) == {"S1", "S2", "S3"}
    # no profiler noise: what is left are the artifact's errors within its certificate
    # (centres +-5 um over ~25 mm between spheres: about 0.01 deg)
    for row in summary["sensors"].values():
        assert row["translation_error_mm"] < 0.03 and row["rotation_error_deg"] < 0.02
        assert row["residual_rms_mm"] < 0.005
    cal = read_calibration_toml(out / "calibration.toml")
    prov = read_calibration_provenance(out / "calibration.toml")
    sc = load_scenario(resolve_scenario("pad"))
    cell_file = CellModel.from_scenario(sc).calibration()
    # T_F_O: the artifact is the work object, its mount co-estimated
    assert prov["T_F_O"].startswith("estimated: the sphere artifact's mount")
    assert summary["T_F_O_error"]["translation_mm"] < 0.02
    assert not np.array_equal(cal.T_F_O, cell_file.T_F_O)
    # T_B_N: the exit 0.8 mm off the cell file, found again by the touch-off
    assert prov["T_B_N"].startswith("estimated: exit position by a nozzle touch-off")
    assert summary["T_B_N_error"]["translation_mm"] < 0.03
    dt_file, _ = pose_error(cal.T_B_N, cell_file.T_B_N)
    assert abs(dt_file - 0.8) < 0.03
    for sid in ("S1", "S2", "S3"):
        assert prov[sid].startswith("estimated: sphere artifact hand-eye solve")
        dt, _ = pose_error(cal.T_B_S[sid], cell_file.T_B_S[sid])
        assert dt > 1.9  # the sensors as built stand 2 mm off the cell file


def test_recorded_rehearsal_is_solved_from_the_recording(tmp_path):
    rec = tmp_path / "calib_run.mcap"
    r = runner.invoke(app, ["calibrate", "--rehearse", "pad", "--poses", "12", "--seed", "4",
                            "--z-scale-error", "0.001", "--fan-angle-deg", "0.05",
                            "--x-distortion-mm", "0.03", "--holdout", "0", "--record", str(rec),
                            "--out", str(tmp_path / "rehearsed")])
    assert r.exit_code == 0, r.output
    recording = read_recording(rec)
    sc = load_scenario(resolve_scenario("pad"))
    # the recording starts from the cell file, never from the truth
    prior = recording.calibration
    nominal = CellModel.from_scenario(sc).calibration()
    for sid in ("S1", "S2", "S3"):
        assert np.allclose(prior.T_B_S[sid], nominal.T_B_S[sid], atol=1e-9)
    out = tmp_path / "out"
    r = runner.invoke(app, ["calibrate", str(rec), "--artifact", "four_spheres", "--holdout",
                            "0", "--out", str(out)])
    assert r.exit_code == 0, r.output
    cal = read_calibration_toml(out / "calibration.toml")
    again = read_calibration_toml(tmp_path / "rehearsed" / "calibration.toml")
    assert read_calibration_provenance(tmp_path / "rehearsed" / "calibration.toml")[
        "T_F_O"].startswith("estimated")
    for sid in ("S1", "S2", "S3"):  # the same solve, from float32 metres (PointCloud2)
        dt, dr = pose_error(cal.T_B_S[sid], again.T_B_S[sid])
        assert dt < 1e-3 and dr < 1e-6, sid
    prov = read_calibration_provenance(out / "calibration.toml")
    assert prov["T_F_O"].startswith("estimated")
    assert "touch-off (4 touches" in prov["T_B_N"]
    assert json.loads((out / "calibration.json").read_text())["n_observations"] == 36
    fixed = tmp_path / "fixed"
    r = runner.invoke(app, ["calibrate", str(rec), "--holdout", "0", "--fixed-mount", "--out",
                            str(fixed)])
    assert r.exit_code == 0, r.output
    prov = read_calibration_provenance(fixed / "calibration.toml")
    assert prov["T_F_O"] == "taken from the calibration in calib_run.mcap"
    assert np.array_equal(read_calibration_toml(fixed / "calibration.toml").T_F_O,
                          prior.T_F_O)


def test_degenerate_recorded_pose_set_exits_2(tmp_path):
    art_path = tmp_path / "one_sphere.toml"
    art_path.write_text('schema = 1\nname = "one"\n[mount]\ntranslation_mm = [0, 0, 0]\n'
                        '[[spheres]]\ncenter_mm = [60, 60, 20]\nradius_mm = 8\n')
    T_B_S = from_rotvec([2.2, 0.3, 0.1], [10.0, -40.0, 90.0])
    cal = Calibration({"S1": T_B_S}, np.eye(4), np.eye(4))
    path = tmp_path / "line.mcap"
    writer = RecordingWriter(path, attachments={})
    writer.write_static_tf(cal)
    for i in range(6):  # the sphere centre moves along one line: rotation about it is free
        c_S = np.array([-10.0 + 4 * i, 4.0, 85.0 + 2 * i])
        T_B_F = np.eye(4)
        T_B_F[:3, 3] = apply(T_B_S, c_S[None])[0] - [60.0, 60.0, 20.0]
        writer.write(RobotState(i, 2 * i, np.zeros(6), T_B_F))
        writer.write(RobotState(i + 0.5, 2 * i + 1, np.zeros(6), T_B_F))
        ang = np.linspace(-2.2, -0.9, 60)
        rho = np.sqrt(64.0 - 16.0)
        xz = np.column_stack([c_S[0] + rho * np.cos(ang), c_S[2] + rho * np.sin(ang)])
        writer.write(Profile("S1", i + 0.25, i, xz, np.ones(60, bool), np.ones(60)))
    writer.close()
    r = runner.invoke(app, ["calibrate", str(path), "--artifact", str(art_path),
                            "--out", str(tmp_path / "o")])
    assert r.exit_code == 2, r.output
    assert "S1: the poses do not constrain" in r.output
    assert not (tmp_path / "o" / "calibration.toml").exists()


def test_artifact_the_sensors_never_see_exits_2(tmp_path):
    r = runner.invoke(app, ["calibrate", "--rehearse", "pad", "--poses", "4",
                            "--mount-error-mm", "200", "--out", str(tmp_path / "o")])
    assert r.exit_code == 2, r.output
    assert "the artifact was seen in 0 of 4 profiles" in r.output
    assert not (tmp_path / "o").exists()


def test_missing_recording_is_refused(tmp_path):
    r = runner.invoke(app, ["calibrate"])
    assert r.exit_code == 2
    assert "give a RECORDING.mcap" in r.output
    r = runner.invoke(app, ["calibrate", str(tmp_path / "absent.mcap")])
    assert r.exit_code == 2
    assert "no such recording" in " ".join(r.output.split())
