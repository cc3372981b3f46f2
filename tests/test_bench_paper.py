"""The paper-table measures on a known surface: a 20 x 10 mm block, 4 mm high at the centre,
3 mm along a 2 mm rim, over 10 layers."""

import numpy as np
import pytest

from dm2.bench.paper import part_heights, plot_track_evolution, track_evolution_figure


def _block_vertices(step=0.25):
    x = np.arange(40.0, 80.0, step) + step / 2
    y = np.arange(40.0, 80.0, step) + step / 2
    gx, gy = np.meshgrid(x, y)
    inside = (np.abs(gx - 60) < 10) & (np.abs(gy - 60) < 5)
    rim = inside & ((np.abs(gx - 60) > 8) | (np.abs(gy - 60) > 3))
    z = np.where(inside, np.where(rim, 3.0, 4.0), 0.0)
    return np.column_stack([gx.ravel(), gy.ravel(), z.ravel()])


def test_part_heights_edge_centre_and_mass():
    v = _block_vertices()
    out = part_heights(v, n_layers=10, density_g_cm3=4.51, edge_band_mm=1.5)
    assert out["edge_height_mm"] == pytest.approx(3.0)
    assert out["centre_height_mm"] == pytest.approx(4.0)
    assert out["avg_centre_layer_mm"] == pytest.approx(0.4)
    volume = 20 * 10 * 3.0 + 16 * 6 * 1.0  # mm^3
    assert out["mass_g"] == pytest.approx(volume * 4.51 / 1000, rel=0.02)
    assert out["coverage"] == 1.0


def test_unobserved_cells_take_their_neighbours_height():
    v = _block_vertices()
    rng = np.random.default_rng(5)
    keep = rng.random(len(v)) > 0.5  # half the vertices missing, as in a sparse scan
    out = part_heights(v[keep], n_layers=10, density_g_cm3=4.51, edge_band_mm=1.5)
    assert out["centre_height_mm"] == pytest.approx(4.0)
    assert out["mass_g"] == pytest.approx((20 * 10 * 3.0 + 16 * 6) * 4.51 / 1000, rel=0.05)


def test_track_evolution_figure_plots_each_track_by_layer(tmp_path):
    report = {"tracks": [
        {"id": 1, "kind": "overbuild", "history": [
            {"layer": k, "area_mm2": 10.0 * k, "max_deviation_mm": 0.2 * k} for k in range(1, 5)]},
        {"id": 2, "kind": "local_underbuild", "history": [  # one layer only: left out
            {"layer": 3, "area_mm2": 5.0, "max_deviation_mm": -0.3}]},
    ]}
    fig = track_evolution_figure(report, "growing overbuild")
    ax_area, ax_height = fig.axes
    (area,), (height,) = ax_area.get_lines(), ax_height.get_lines()
    np.testing.assert_array_equal(area.get_xdata(), [1, 2, 3, 4])
    np.testing.assert_allclose(area.get_ydata(), [10.0, 20.0, 30.0, 40.0])
    np.testing.assert_allclose(height.get_ydata(), [0.2, 0.4, 0.6, 0.8])
    assert area.get_label() == "#1 overbuild" and ax_area.get_title() == "growing overbuild"
    path = plot_track_evolution(tmp_path / "t.png", report, "growing overbuild")
    from matplotlib.image import imread

    assert imread(path).shape[:2] == (660, 770)  # 7 x 6 in at 110 dpi
