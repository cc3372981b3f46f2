"""A wrong hand-eye calibration shows in the reconstruction; the solved one removes it."""

from __future__ import annotations

import pytest
from typer.testing import CliRunner

from dm2.cli.main import app
from dm2.core.calibration_io import write_calibration_toml
from dm2.core.config import load_scenario
from scenarios import resolve_scenario


def median_rms(run) -> float:
    rms = sorted(v["rms_mm"] for v in run.reconstruction.values())
    return rms[len(rms) // 2]


@pytest.mark.slow
def test_solved_calibration_removes_the_miscalibration_error(tmp_path):
    from dm2.cli.bench_runner import run_scenario
    from dm2.core.calibration_io import read_calibration_toml
    from twin.stream.simulate import Simulation

    sc = load_scenario(resolve_scenario("pad_miscalibrated"))
    sc = sc.model_copy(update={"duration_s": 20.0})
    res = CliRunner().invoke(app, ["calibrate", "--rehearse", "pad_miscalibrated", "--poses",
                                   "48", "--noise-mm", "0.03", "--robot-noise-mm", "0.02",
                                   # the build's twin stands at the nominal layout: so does
                                   # the rehearsal's (the prior is still the cell file)
                                   "--as-built-mm", "0", "--as-built-deg", "0",
                                   "--out", str(tmp_path / "cal")])
    assert res.exit_code == 0, res.output
    solved = read_calibration_toml(tmp_path / "cal" / "calibration.toml")
    write_calibration_toml(Simulation(sc).true_calibration, tmp_path / "true.toml")
    true = read_calibration_toml(tmp_path / "true.toml")

    wrong = median_rms(run_scenario(sc, tmp_path / "wrong"))
    fixed = median_rms(run_scenario(sc, tmp_path / "fixed", calibration=solved))
    ideal = median_rms(run_scenario(sc, tmp_path / "ideal", calibration=true))
    assert wrong > 1.4 * fixed  # the miscalibration is visible in the reconstruction
    assert fixed == pytest.approx(ideal, abs=0.01)  # and the solved calibration removes it
