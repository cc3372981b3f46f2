"""``dm2 bench --calibration rehearsed``: the calibration the chain monitors with is solved on a
twin whose sensors stand off the nominal layout, from the cell file, never from the truth."""

from __future__ import annotations

import numpy as np
import pytest

from dm2.bench.suites import load_suite_scenario
from dm2.core.frames import pose_error
from scenarios import scenario_dir
from twin.cell.cell import CellModel


@pytest.mark.slow
def test_rehearsed_calibration_of_a_bench_scenario():
    from dm2.cli.bench_calibration import AS_BUILT_DEG, AS_BUILT_MM, rehearsed_calibration

    sc = load_suite_scenario(scenario_dir() / "suites" / "smoke" / "control.toml", [])
    true_T_B_S, outcome, info = rehearsed_calibration(sc)
    nominal = CellModel.from_scenario(sc).calibration()
    for sid in ("S1", "S2", "S3"):
        dt, dr = pose_error(true_T_B_S[sid], nominal.T_B_S[sid])
        assert dt == pytest.approx(AS_BUILT_MM) and np.degrees(dr) == pytest.approx(AS_BUILT_DEG)
        e = info["errors"][sid]
        assert e["translation_error_mm"] <= 0.05 and e["rotation_error_deg"] <= 0.02, sid
    # the mount and the nozzle are estimated, and close to the twin's (nominal) ones
    assert outcome.provenance["T_F_O"].startswith("estimated")
    assert outcome.provenance["T_B_N"].startswith("estimated")
    assert info["errors"]["T_F_O"]["translation_error_mm"] < 0.05
    assert info["errors"]["T_B_N"]["translation_error_mm"] < 0.05
    assert not np.array_equal(outcome.calibration.T_F_O, nominal.T_F_O)
