"""A fault-free build on a twin whose efficiency falls linearly with the impact angle (the
monitor models cos^2), 15 % less efficient and with a 10 % narrower plume: the edges of the box
come out systematically lower than the Gaussian model predicts. The layers' own deviations raise
the plume term's convex bound, and no track opens; with the bound as configured, the same run
opens false underbuild tracks at the box's edges."""

from __future__ import annotations

import numpy as np
import pytest

from dm2.cli.bench_runner import run_scenario
from dm2.core.config import parse_scenario
from dm2.defects import deviation as deviation_mod
from dm2.defects.uncertainty_online import FACTORS


def _scenario():
    return parse_scenario({
        "schema": 1, "name": "linear_curve_control", "seed": 223,
        "part": {"generator": "box",
                 "params": {"width_mm": 28.0, "depth_mm": 20.0, "height_mm": 2.4}},
        "process": {"feed_g_min": 26.0},
        "twin_process": {"plume_sigma_factor": 0.90, "efficiency_factor": 0.85,
                         "efficiency_curve": "linear"},
        "noise": {"range_sigma_mm": 0.05}}, "linear_curve_control")


@pytest.mark.slow
def test_the_layers_raise_the_bound_where_the_model_errs_and_no_track_opens(tmp_path,
                                                                            monkeypatch):
    run = run_scenario(_scenario(), tmp_path / "raised", full_report=False)
    layers = run.report["layers"]
    factors = [lay["statistics"]["uncertainty_inflation"] for lay in layers]
    assert all(set(f) == set(FACTORS) for f in factors)
    assert factors[-1]["plume_convex"] > 1.5  # the edges: the linear curve loses material
    assert all(f["wall"] == 1.0 and f["foot"] == 1.0 for f in factors)
    assert run.report["tracks"] == []
    truth = run.fault_truth["faults"]
    assert truth == []  # fault-free: every track would be false

    # the same run with the bound as configured: the edges open false underbuild tracks
    monkeypatch.setattr(deviation_mod, "model_inflation",
                        lambda *a, **k: dict.fromkeys(FACTORS, 1.0))
    plain = run_scenario(_scenario(), tmp_path / "configured", full_report=False)
    tracks = plain.report["tracks"]
    assert tracks and all(t["kind"] == "underbuild" for t in tracks)
    for t in tracks:
        x, y, _ = t["history"][-1]["centroid_O_mm"]
        # on the box's rim (x 46-74, y 50-70 mm), not on its plateau
        assert min(abs(x - 46.0), abs(x - 74.0), abs(y - 50.0), abs(y - 70.0)) < 6.0
    assert np.isclose(layers[0]["statistics"]["n_vertices"],
                      plain.report["layers"][0]["statistics"]["n_vertices"])
