"""A scenario whose [twin_process] differs from [process]: the twin's part changes, the
monitor's near-net reference (nominal [process]) stays bit for bit the same."""

from __future__ import annotations

import numpy as np
import pytest

from dm2.cli.bench_runner import run_scenario
from dm2.core.config import parse_scenario

NOMINAL_TWIN = {"plume_sigma_factor": 1.0, "efficiency_factor": 1.0, "efficiency_curve": "cos2",
                "plume_exponent": 2.0, "porosity": 0.0, "standoff_efficiency_per_mm": 0.0}


def _scenario(twin: dict):
    return parse_scenario({
        "schema": 1, "name": "twin_vs_nominal", "seed": 3, "duration_s": 9.0,
        "part": {"generator": "pad", "params": {"width_mm": 12.0, "depth_mm": 8.0,
                                                "height_mm": 1.6}},
        "toolpath": {"strategy": "single", "contour_angle_deg": 0.0},
        "process": {"feed_g_min": 26.0}, "twin_process": twin}, "twin_vs_nominal")


def test_twin_process_changes_the_part_not_the_reference(tmp_path):
    runs = {}
    for name, twin in (("nominal", NOMINAL_TWIN),
                       ("twin", {**NOMINAL_TWIN, "efficiency_factor": 0.85,
                                 "plume_sigma_factor": 1.1})):
        from dm2.pipeline import session as session_mod

        seen = []
        orig = session_mod.MonitoringSession.__init__

        def spy(self, *a, _seen=seen, _orig=orig, **kw):
            _orig(self, *a, **kw)
            _seen.append(self)

        session_mod.MonitoringSession.__init__ = spy
        try:
            run = run_scenario(_scenario(twin), tmp_path / name, full_report=False)
        finally:
            session_mod.MonitoringSession.__init__ = orig
        runs[name] = (run, seen[0])
    (nom, s_nom), (twin, s_twin) = runs["nominal"], runs["twin"]
    assert s_nom.reference.process == s_twin.reference.process  # the nominal [process]
    ref_nom = s_nom.reference.snapshot().heights_mm
    ref_twin = s_twin.reference.snapshot().heights_mm
    assert np.array_equal(ref_nom, ref_twin)
    last = max(int(p.stem[-3:]) for p in (nom.run_dir / "truth").glob("deviation_*.npz"))
    surf = {}
    for name, run in (("nominal", nom), ("twin", twin)):
        with np.load(run.run_dir / "truth" / f"deviation_{last:03d}.npz") as z:
            surf[name] = z["surface_mm"].astype(np.float64)
            assert not z["deviation_mm"].any()  # no faults: no fault-caused deviation
    # 15 % less sticks: the twin's part holds about 15 % less material
    assert surf["twin"].sum() / surf["nominal"].sum() == pytest.approx(0.85, abs=0.02)
