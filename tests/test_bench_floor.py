"""The floor the bench can measure follows the run's own event tolerance
(dm2.bench.scoring ``event_tolerance_mm``), and a sweep runs the fault-free control over the
same seeds beside every size (dm2.bench.sweep)."""

import numpy as np
import pytest
from test_bench_scoring import GX, GY, LAYERS, blob, footprints, maps, report, truth

from dm2.bench.scoring import score_run
from dm2.bench.suite_score import summarize
from dm2.bench.sweep import summarize_sweep, sweep_cases

DEV = {k: (blob(25.0, 14.0, 0.4) if k >= 1 else np.zeros_like(GX)) for k in LAYERS}


def test_a_fault_under_half_a_millimetre_qualifies_at_a_lower_tolerance():
    """A 0.4 mm bump from layer 1 and a track on it from layer 2: at the default 0.5 mm it
    does not qualify (the track is neutral); at a 0.25 mm tolerance it does, from layer 1, and
    the track detects it with a delay of one layer; a far track stays false either way."""
    on = blob(25.0, 14.0, 0.4) >= 0.25
    far = (np.abs(GX - 12.0) <= 1.5) & (np.abs(GY - 25.0) <= 1.5)
    tracks = {1: ("local_overbuild", {2: on, 3: on}), 2: ("overbuild", {2: far})}
    args = dict(truth_maps=maps(DEV), footprints=footprints(tracks))
    fault = truth("bump", 1, [[25.0, 14.0]])
    at_half = score_run(report(tracks), fault, **args)
    assert not at_half["faults"][0]["qualifies"] and at_half["neutral_tracks"] == [1]
    assert at_half["false_tracks"] == [2] and at_half["event_tolerance_mm"] == 0.5
    low = score_run(report(tracks), fault, event_tolerance_mm=0.25, **args)
    (f,) = low["faults"]
    assert f["qualifies"] and f["onset_layer"] == 1 and f["detected"]
    assert f["first_layer_detected"] == 2 and f["onset_delay_layers"] == 1
    assert f["peak_height_mm"] == pytest.approx(0.4, abs=0.01)
    assert low["true_tracks"] == [1] and low["false_tracks"] == [2]
    summ = summarize({"bump": low})
    assert summ["recall"] == 1.0 and summ["event_tolerance_mm"] == [0.25]
    assert "event tolerance (0.25 mm)" in summ["definition"]


def test_a_sweep_runs_the_fault_free_control_over_the_same_seeds():
    base = {"name": "b", "seed": 1, "monitor": {"delta_global_mm": 0.25},
            "faults": [{"kind": "bump", "height_mm": 1.0}, {"kind": "dent", "depth_mm": 1.0}]}
    cases = sweep_cases(base, [0.2, 0.6], [5, 6], controls=True)
    assert [(c["size"], c["seed"], c.get("control", False)) for c in cases] == [
        (0.2, 5, False), (0.2, 6, False), (0.6, 5, False), (0.6, 6, False),
        (None, 5, True), (None, 6, True)]
    ctrl = cases[-1]["scenario"]
    assert ctrl["faults"] == [] and ctrl["seed"] == 6 and ctrl["monitor"] == base["monitor"]
    assert ctrl["name"] == "b_control_seed6" and len(base["faults"]) == 2
    assert len(sweep_cases(base, [0.2], [5])) == 1  # no controls unless asked
    res = [{"size": 0.2, "seed": 5, "detected": False, "sign_ok": False,
            "false_positive_tracks": 1, "realtime_false_alarms": 0},
           {"size": 0.2, "seed": 6, "detected": True, "sign_ok": True,
            "false_positive_tracks": 0, "realtime_false_alarms": 2},
           {"size": None, "seed": 5, "control": True, "false_positive_tracks": 0,
            "realtime_false_alarms": 3, "drift_tracks": 1},
           {"size": None, "seed": 6, "control": True, "false_positive_tracks": 2,
            "realtime_false_alarms": 0}]
    summ = summarize_sweep(res)
    (row,) = summ["by_size"]
    assert row["size"] == 0.2 and row["n"] == 2 and row["probability"] == 0.5
    assert row["false_positive_tracks"] == 1 and row["realtime_false_alarms"] == 2
    assert summ["control"] == {"n": 2, "seeds": [5, 6], "false_tracks": 2, "drift_tracks": 1,
                               "realtime_false_alarms": 3}
    assert summarize_sweep(res[:2])["control"] is None
