"""Finished layers' arrays on disk (dm2.io.spill): the same results, bit for bit."""

import gc
import pickle

import numpy as np
from test_deviation import CELL, MON, gaussian, pad_heights, top_surface

from dm2.defects.layer_analysis import LayerAnalysis
from dm2.io.spill import Spilled
from dm2.reference.height_map import ReferenceMap
from dm2.report import ReportContent, write_report

CENTRE = (50.0, 70.0)


def _build(layers_in_memory):
    """Six layers of a pad with a bump growing from layer 2 (0.6 mm + 0.2 mm a layer)."""
    mon = LayerAnalysis(MON.model_copy(update={"layers_in_memory": layers_in_memory}))
    for layer in range(6):
        ref_h, xx, yy = pad_heights(layer)
        meas = ref_h + (gaussian(xx, yy, CENTRE, 0.6 + 0.2 * layer, 5.0) if layer >= 2 else 0)
        mon.analyse_layer(top_surface(meas), ReferenceMap(ref_h, CELL, layer))
    mon.finish()
    return mon


def _arrays(dev):
    dev = dev.load() if isinstance(dev, Spilled) else dev
    return {k: v for k, v in vars(dev).items() if isinstance(v, np.ndarray)}


def test_spilled_layers_read_back_bit_for_bit_and_hold_no_arrays():
    kept, spilled = _build(None), _build(1)
    assert [type(r.deviation) for r in spilled.results] == [Spilled] * 5 + \
        [type(kept.results[-1].deviation)]
    for a, b in zip(kept.results, spilled.results, strict=True):
        assert (a.layer, a.track_ids) == (b.layer, b.track_ids)
        arrays_a, arrays_b = _arrays(a.deviation), _arrays(b.deviation)
        assert arrays_a.keys() == arrays_b.keys() and len(arrays_a) >= 8
        for key in arrays_a:
            assert np.array_equal(arrays_a[key], arrays_b[key]), key
        assert a.statistics() == b.statistics()
    # the one track: the bump, overbuild from layer 2 to the last, in both
    (track,) = spilled.tracker.tracks
    assert (track.kind, track.first_layer, track.last_layer) == ("overbuild", 2, 5)
    proxy = spilled.results[0].deviation
    assert not any(isinstance(getattr(proxy, s, None), np.ndarray) for s in proxy.__slots__)
    assert proxy.path.stat().st_size > 0
    # pickled (as to the live report's child process) it stays a path and reads the same
    again = pickle.loads(pickle.dumps(proxy))
    assert isinstance(again, Spilled) and again.path == proxy.path
    assert np.array_equal(again.signed_distance_mm, kept.results[0].deviation.signed_distance_mm)


def test_report_from_spilled_layers_is_the_same(tmp_path):
    kept, spilled = _build(None), _build(1)
    reports = []
    for name, mon in (("kept", kept), ("spilled", spilled)):
        reports.append(write_report(tmp_path / name, mon.results, mon.tracker.tracks,
                                    ReportContent(config_toml='name = "x"\n', timing={})))
    for rep in reports:
        rep.pop("files", None)
        rep.get("meta", {}).pop("written_at", None)
        for layer in rep["layers"]:
            layer.pop("timing_s")  # wall seconds
    assert reports[0]["tracks"] == reports[1]["tracks"]
    assert reports[0]["layers"] == reports[1]["layers"]
    for ply in sorted((tmp_path / "kept" / "meshes").glob("layer_*.ply")):
        assert ply.read_bytes() == (tmp_path / "spilled" / "meshes" / ply.name).read_bytes()


def test_scratch_folder_goes_with_the_results():
    mon = _build(1)
    folder = mon.spill.folder
    # five deviations and five references
    assert len(list(folder.glob("LayerDeviation_*.pickle"))) == 5
    assert len(list(folder.glob("ReferenceMap_*.pickle"))) == 5
    del mon
    gc.collect()
    assert not folder.exists()
