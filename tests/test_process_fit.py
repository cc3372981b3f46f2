"""The reference follows the process: a bounded, rate-limited deposition scale, and what it
absorbs is reported as a process finding."""

from types import SimpleNamespace

import numpy as np
import pytest

from dm2.pipeline.process_fit import ProcessFit

LAYER_MM = 0.8


def layer(k, measured_mm, reference_mm, n=400):
    xy = np.random.default_rng(k).uniform(50, 70, (n, 2))
    dev = SimpleNamespace(vertices_O=np.column_stack([xy, np.full(n, measured_mm)]),
                          foot_O=np.column_stack([xy, np.full(n, reference_mm)]),
                          class_code=np.zeros(n, np.int8), outside_mm=np.zeros(n),
                          normals_O=np.tile([0.0, 0.0, 1.0], (n, 1)), n_vertices=n)
    return SimpleNamespace(layer=k, deviation=dev)


def build(true_scale_of_layer, layers=8):
    """Measured and reference top heights of a pad whose reference deposits at the fit's
    scale; returns the fit and the deviation per layer."""
    fit = ProcessFit(planned_height_mm=layers * LAYER_MM)
    meas = ref = 0.0
    devs = []
    for k in range(layers):
        meas += LAYER_MM * true_scale_of_layer(k)
        ref += LAYER_MM * fit.scale
        fit.update(layer(k, meas, ref))
        devs.append(meas - ref)
    return fit, np.array(devs)


def test_systematic_offset_is_absorbed_at_the_documented_rate_and_reported():
    fit, devs = build(lambda k: 0.92)
    scales = [e["next_scale"] for e in fit.layers]
    assert np.all(np.abs(np.diff([1.0, *scales])) <= fit.rate_per_layer + 1e-12)
    assert scales[-1] == pytest.approx(0.92, abs=0.005)
    assert devs.min() > -0.4  # never an underbuild beyond delta_global_mm
    (finding,) = fit.findings()
    # the first layer (on the bare plate) is not an estimate: the finding starts at layer 1
    assert finding.startswith("deposition efficiency 8 % below nominal since layer 1")
    assert "ends 0.5 mm short" in finding
    layers = fit.summary()["layers"]
    assert layers[0]["estimate"] is None and layers[1]["estimate"] == pytest.approx(0.92)


def test_fast_drift_is_not_absorbed_beyond_the_bound():
    fit, devs = build(lambda k: max(1.0 - 0.3 * k, 0.1))
    assert min(e["next_scale"] for e in fit.layers) == pytest.approx(1 - fit.bound)
    assert devs[2] < -0.4 and np.all(np.diff(devs[1:]) < 0)  # the defect keeps growing


def test_nominal_process_gives_no_finding():
    fit, devs = build(lambda k: 1.0 + 0.02 * (-1) ** k)  # +-2 % noise per layer
    assert fit.findings() == [] and np.abs(devs).max() < 0.1


def test_first_layer_shortfall_alone_is_no_finding():
    fit, devs = build(lambda k: 0.87 if k == 0 else 1.0)
    assert fit.findings() == []  # the process estimate leaves the first layer out
    assert [e["estimate"] for e in fit.layers[1:]] == pytest.approx([1.0] * 7)
    assert [e["next_scale"] for e in fit.layers] == pytest.approx([1.0] * 8)
    assert np.allclose(devs, -0.8 * 0.13)  # the first layer's shortfall stays as it was


def test_process_finding_is_in_the_verdict_not_a_defect():
    from dm2.report.summary import verdict

    fit, _ = build(lambda k: 0.92)
    report = {"tracks": [], "layers": [{"layer": k} for k in range(8)],
              "process": fit.summary()}
    v = verdict(report)
    assert v["headline"].startswith("No defect found in 8 layers") and v["defects"] == 0
    assert v["sentences"] == [f"Process finding: {fit.findings()[0]}."]
    assert "8 % below nominal since layer 1" in v["sentences"][0]
