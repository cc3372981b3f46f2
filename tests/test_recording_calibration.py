"""Calibration TOML: exact round trip and errors that name the file and the field."""

from __future__ import annotations

import re

import numpy as np
import pytest

from dm2.core.calibration_io import (
    calibration_from_toml,
    calibration_to_toml,
    read_calibration_toml,
    write_calibration_toml,
)
from dm2.core.config import ConfigError
from dm2.core.frames import from_euler_deg
from dm2.core.messages import Calibration


def _cal(seed: int = 11) -> Calibration:
    rng = np.random.default_rng(seed)
    poses = [from_euler_deg(rng.normal(0, 500.0, 3), rng.uniform(-180, 180, 3)) for _ in range(5)]
    return Calibration(T_B_S={"S1": poses[0], "S2": poses[1], "S3": poses[2]},
                       T_F_O=poses[3], T_B_N=poses[4])


def test_round_trip_is_exact(tmp_path):
    cal = _cal()
    path = tmp_path / "cal.toml"
    write_calibration_toml(cal, path)
    back = read_calibration_toml(path)
    for a, b in [(cal.T_B_N, back.T_B_N), (cal.T_F_O, back.T_F_O)] + [
            (cal.T_B_S[s], back.T_B_S[s]) for s in ("S1", "S2", "S3")]:
        np.testing.assert_array_equal(a[:3, 3], b[:3, 3])  # repr floats: bit for bit
        np.testing.assert_allclose(a[:3, :3], b[:3, :3], rtol=0, atol=1e-15)
    # the file's own numbers survive a second write unchanged (to the last bit or so)
    text2 = calibration_to_toml(back)
    again = calibration_from_toml(text2)
    np.testing.assert_allclose(again.T_B_S["S2"], back.T_B_S["S2"], rtol=0, atol=1e-15)
    assert "[sensors.S1]" in path.read_text() and "quaternion_wxyz" in path.read_text()


def test_documented_example_reads_with_units():
    text = """schema = 1
[T_B_N]
translation_mm = [1300.0, 0.0, 900.0]
quaternion_wxyz = [0.0, 1.0, 0.0, 0.0]
[T_F_O]
translation_mm = [-60, -60, 150]
quaternion_wxyz = [1, 0, 0, 0]
[sensors.S2]
translation_mm = [1.0, 2.0, 3.0]
quaternion_wxyz = [0.7071067811865476, 0.0, 0.0, 0.7071067811865476]
"""
    cal = calibration_from_toml(text, "x.toml")
    np.testing.assert_allclose(cal.T_B_N[:3, 2], [0, 0, -1], atol=1e-15)  # nozzle points down
    np.testing.assert_allclose(cal.T_B_S["S2"][:3, 0], [0, 1, 0], atol=1e-15)  # 90 deg about z
    assert set(cal.T_B_S) == {"S2"}


GOOD = calibration_to_toml(_cal())


@pytest.mark.parametrize("edit, field", [
    (lambda t: t.replace("[T_F_O]", "[T_F_X]"), "T_F_X"),
    (lambda t: t.replace("schema = 1", "schema = 9"), "schema"),
    (lambda t: t.replace("[sensors.S3]", "[sensors.S7]"), "sensors.S7"),
    (lambda t: t.replace("[T_B_N]\ntranslation_mm = [", "[T_B_N]\ntranslation_mm = [1.0, "),
     "T_B_N.translation_mm"),
    (lambda t: t.replace("[sensors.S2]\n", "[sensors.S2]\nscale = 2.0\n"), "sensors.S2.scale"),
    (lambda t: re.sub(r"(\[T_F_O\]\ntranslation_mm = .*\n)quaternion_wxyz = .*\n", r"\1", t),
     "T_F_O.quaternion_wxyz': missing"),
    (lambda t: t.replace("[sensors.S1]\ntranslation_mm = [",
                         '[sensors.S1]\ntranslation_mm = ["a", '),
     "sensors.S1.translation_mm"),
    (lambda t: t + "\n[oops", "not valid TOML"),
])
def test_bad_files_name_the_field(tmp_path, edit, field):
    path = tmp_path / "bad_cal.toml"
    path.write_text(edit(GOOD))
    with pytest.raises(ConfigError) as err:
        read_calibration_toml(path)
    assert "bad_cal.toml" in str(err.value)
    assert field in str(err.value)


def test_non_unit_quaternion_and_missing_file(tmp_path):
    text = GOOD.replace("[T_B_N]\ntranslation_mm", "[T_B_N]\nquaternion_wxyz = [1.0, 0.0, 0.0, "
                        "0.1]\ntranslation_mm")
    lines = text.splitlines()
    # drop the original T_B_N quaternion (the line after translation_mm in that table)
    i = lines.index("[T_B_N]")
    del lines[i + 3]
    with pytest.raises(ConfigError, match="T_B_N.quaternion_wxyz.*unit"):
        calibration_from_toml("\n".join(lines), "c.toml")
    with pytest.raises(ConfigError, match="nope.toml"):
        read_calibration_toml(tmp_path / "nope.toml")
