"""Advise mode (dm2.control.advisor): the next layer corrected from a measured top, written as
a RAPID module and a CSV that read back to the same speeds."""

import numpy as np
import pytest

from dm2.control.advisor import Compensator
from dm2.core.config import ControlConfig
from dm2.core.messages import Toolpath
from dm2.toolpath.formats import read_csv, read_rapid

LAYER_MM = 0.8


def _raster(n_layers=3):
    """Per layer: an approach and five 8 mm lines along x at y 10..18, at z = layer * 0.8."""
    rows = []
    for k in range(n_layers):
        for j, y in enumerate(np.arange(10.0, 20.0, 2.0)):
            xs = (0.0, 8.0, 16.0, 24.0, 32.0) if j % 2 == 0 else (32.0, 24.0, 16.0, 8.0, 0.0)
            for i, x in enumerate(xs):
                rows.append((x, y, k * LAYER_MM, k, not (i == 0 and j == 0)))
    a = np.array(rows, dtype=float)
    n = len(a)
    return Toolpath(a[:, :3], np.tile([0.0, 0.0, -1.0], (n, 1)), np.full(n, 30.0),
                    np.zeros(n, np.int8), a[:, 3].astype(np.int32), a[:, 4].astype(bool),
                    np.full(n, 1.0))


def _top_vertices(short_mm, x_range=(8.0, 24.0)):
    """A fused top after layer 0 (at 0.8 mm) on a 0.25 mm grid, ``short_mm`` low in x_range."""
    x, y = np.meshgrid(np.arange(-4.0, 36.0, 0.25), np.arange(5.0, 24.0, 0.25))
    z = np.full_like(x, LAYER_MM)
    z[(x >= x_range[0]) & (x <= x_range[1])] -= short_mm
    verts = np.c_[x.ravel(), y.ravel(), z.ravel()]
    return verts, np.tile([0.0, 0.0, 1.0], (len(verts), 1)), np.full(len(verts), 5.0)


def test_the_next_layer_is_corrected_and_its_rapid_module_reads_back_the_same_speeds(tmp_path):
    tp = _raster()
    cfg = ControlConfig(rate_per_layer=1.0, sample_sigma_mm=0.5)
    comp = Compensator(tp, cfg, LAYER_MM, tmp_path / "corrections")
    corr = comp.correct_next(0, *_top_vertices(0.5))
    assert corr.layer == 1
    predicted = LAYER_MM / (LAYER_MM + cfg.gain * 0.5)
    mid_x = corr.midpoint_O[:, 0]
    inside = corr.spray_on & (np.abs(mid_x - 16.0) < 5.0) & (np.abs(corr.midpoint_O[:, 1]
                                                                   - 14.0) < 3.0)
    assert inside.sum() == 6  # the middle moves (x 12 and 20) of the three inner lines
    np.testing.assert_allclose(corr.factor[inside], predicted, atol=1e-4)
    outside = corr.spray_on & ((mid_x < 4.5) | (mid_x > 27.5))
    np.testing.assert_allclose(corr.factor[outside], 1.0)
    # layers 0 and 2 as programmed; only layer 1's speeds changed
    other = tp.layer != 1
    np.testing.assert_array_equal(comp.toolpath.speed_mm_s[other], tp.speed_mm_s[other])
    np.testing.assert_array_equal(comp.toolpath.position_O, tp.position_O)
    # the files: one RAPID module and one CSV for layer 1, the same speeds and geometry
    files = sorted(p.name for p in (tmp_path / "corrections").iterdir())
    assert files == ["layer_0001.csv", "layer_0001.mod"]
    layer1 = comp.layer_toolpath(1)
    mod = read_rapid(tmp_path / "corrections" / "layer_0001.mod")
    np.testing.assert_array_equal(mod.speed_mm_s, layer1.speed_mm_s)
    np.testing.assert_array_equal(mod.layer, np.ones(len(layer1), np.int32))
    np.testing.assert_allclose(mod.position_O, layer1.position_O, atol=5e-4)
    np.testing.assert_array_equal(mod.spray_on, layer1.spray_on)
    csv = read_csv(tmp_path / "corrections" / "layer_0001.csv")
    np.testing.assert_array_equal(csv.speed_mm_s, layer1.speed_mm_s)
    # 0.5 mm short: 30 mm/s x 0.8 / (0.8 + 0.8 x 0.5) = 20 mm/s exactly over the short stretch
    np.testing.assert_array_equal(np.unique(mod.speed_mm_s), [20.0, 30.0])


def test_the_summary_and_the_rate_limit_over_layers():
    tp = _raster()
    comp = Compensator(tp, ControlConfig(sample_sigma_mm=0.5), LAYER_MM)  # rate 0.2
    comp.correct_next(0, *_top_vertices(0.5))
    verts, normals, weight = _top_vertices(0.5)
    verts[:, 2] += LAYER_MM  # layer 1 laid 0.8 mm: still 0.5 mm short there
    comp.correct_next(1, verts, normals, weight)
    assert comp.correct_next(2, verts, normals, weight) is None  # no layer 3
    s = comp.summary("advise")
    assert [entry["layer"] for entry in s["layers"]] == [1, 2]
    assert s["layers"][0]["min_factor"] == pytest.approx(0.8, abs=1e-4)
    predicted = LAYER_MM / (LAYER_MM + 0.8 * 0.5)
    assert s["layers"][1]["min_factor"] == pytest.approx(max(predicted, 0.6), abs=1e-4)
    assert s["layers"][0]["mean_error_mm"] > 0 and s["layers"][0]["sped_up_segments"] == 0
