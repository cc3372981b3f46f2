"""End to end on the twin: fault-free pad gives no global track; an injected bump is tracked.

Slow (a full simulated build, fused and analysed): run with ``pytest -m slow``.
"""

import numpy as np
import pytest

import twin  # noqa: F401  (registers the twin's scenario sections with load_scenario)
from dm2.core.config import load_scenario, parse_scenario
from dm2.defects.layer_analysis import LayerAnalysis
from dm2.fusion.fusion import TsdfFusion
from dm2.reference.model import NearNetReference
from dm2.report.report_json import compare_with_truth

pytestmark = pytest.mark.slow


def _monitor_build(scenario):
    from twin.stream.simulate import Simulation

    sim = Simulation(scenario)
    mon = TsdfFusion(sim.calibration, scenario.monitor, scenario.process)
    ref = NearNetReference(scenario.process, scenario.monitor, sim.calibration,
                           size_mm=scenario.cell.plate_size_mm[:2])
    for msg in sim.messages(None, None):
        mon.feed(msg)
        ref.feed(msg)
    mon.finish()
    ref.end_layer()
    dm = LayerAnalysis(scenario.monitor)
    for ls in mon.layer_done:
        if ls.surface.n_vertices:
            dm.analyse_layer(ls.surface, ref.layers[ls.layer])
    dm.finish()
    return dm


def _pad(**extra):
    from scenarios import resolve_scenario

    base = load_scenario(resolve_scenario("pad")).to_toml_dict()
    base.update(extra)
    return parse_scenario(base, "pad (test)")


def test_fault_free_pad_has_no_global_track():
    dm = _monitor_build(_pad())
    assert len(dm.results) == 5
    glob = [t for t in dm.tracker.tracks if not t.kind.startswith("local_")]
    assert glob == []
    for r in dm.results:
        assert abs(r.statistics()["deviation_mean_mm"]) < 0.1


def test_injected_bump_is_tracked_as_overbuild():
    fault = {"kind": "bump", "center_O_mm": [56.0, 60.0], "height_mm": 1.0, "width_mm": 5.0,
             "layers": [2, 2]}
    dm = _monitor_build(_pad(faults=[fault]))
    over = [t for t in dm.tracker.tracks if t.kind == "overbuild"]
    assert over, [t.to_dict() for t in dm.tracker.tracks]
    (match,) = [m for m in compare_with_truth(over, [fault]) if m["detected"]]
    track = next(t for t in over if t.id == match["track_id"])
    assert track.first_layer in (2, 3)  # the blob lands when layer 2 ends: seen in layer 3
    h = track.history[0]
    assert np.hypot(h["centroid_O_mm"][0] - 56.0, h["centroid_O_mm"][1] - 60.0) < 2.0
    assert 0.7 <= h["max_deviation_mm"] <= 1.6  # the 1 mm blob, sprayed over by one layer
    # box height: the bump over the (rippled) reference beneath it
    assert h["max_deviation_mm"] - 0.05 <= h["height_mm"] <= h["max_deviation_mm"] + 0.5
