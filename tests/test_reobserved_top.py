"""The calibration layer's top seen again after its close: only points on the finished plateau,
in the window, count; the estimate recovers a known scale, and the process fit recalibrates on
it while later layers still measure the growth since the fused calibration layer."""

from types import SimpleNamespace

import numpy as np
import pytest

from dm2.defects.classify import CLASS_NAMES
from dm2.process.process_fit import ProcessFit
from dm2.process.reobserved_top import MIN_CELLS, ReobservedTop
from dm2.reference.height_map import ReferenceMap

CELL_MM = 0.25
OVER = CLASS_NAMES.index("overbuild")


def pad_map(height_mm=0.8):
    """A 20 x 10 mm pad at (40..60, 40..50) mm with 2 mm ramps on a 100 x 100 mm plate."""
    c = (np.arange(400) + 0.5) * CELL_MM
    x, y = np.meshgrid(c, c)
    rise = np.clip(np.minimum.reduce([x - 38, 62 - x, y - 38, 52 - y]) / 2.0, 0.0, 1.0)
    return ReferenceMap(height_mm * rise, CELL_MM, 0, 10.0)


def points_on(xy_mm, z_mm):
    return np.column_stack([xy_mm, np.broadcast_to(z_mm, len(xy_mm))])


def grid_xy(x0, x1, y0, y1, step=0.25):
    gx, gy = np.meshgrid(np.arange(x0, x1, step) + 0.1, np.arange(y0, y1, step) + 0.1)
    return np.column_stack([gx.ravel(), gy.ravel()])


def test_the_finished_plateau_seen_in_the_window_gives_the_scale():
    close = pad_map()
    top = ReobservedTop(close, since_s=10.0, until_s=15.0)
    live = close.heights_mm.copy()
    plateau = grid_xy(41, 59, 41, 49)  # 72 x 32 cells, all on the plateau
    top.observe(points_on(plateau, 0.8 * 1.06), 11.0, live)  # the finished top: 6 % taller
    # not counted: before the window, after it, on the ramps, where the spray is back
    top.observe(points_on(plateau, 5.0), 10.0, live)
    top.observe(points_on(plateau, 5.0), 15.5, live)
    top.observe(points_on(grid_xy(38.5, 39.5, 41, 49), 5.0), 12.0, live)
    grown = live.copy()
    grown[160:180, :] += 0.2
    top.observe(points_on(grid_xy(41, 59, 40, 45), 5.0), 13.0, grown)  # rows 160-179 grew
    ratio, cells = top.estimate()
    assert cells == 72 * 32
    assert ratio == pytest.approx(1.06, abs=1e-9)
    # cells next to a flagged defect are left out
    near = np.hypot(*(np.floor(plateau / CELL_MM) * CELL_MM + CELL_MM / 2 - [50.0, 45.0]).T)
    ratio, cells = top.estimate(defect_xy_O=np.array([[50.0, 45.0]]))
    assert ratio == pytest.approx(1.06, abs=1e-9)
    assert cells == 72 * 32 - np.count_nonzero(near <= 1.0) and np.count_nonzero(near <= 1.0)


def test_too_little_seen_gives_no_estimate():
    close = pad_map()
    top = ReobservedTop(close, 10.0, 15.0)
    few = grid_xy(41, 59, 41, 49)[: MIN_CELLS - 1]
    top.observe(points_on(few, 0.85), 11.0, close.heights_mm)
    assert top.estimate() == (None, MIN_CELLS - 1)


def calibration_layer(measured_mm, reference_mm, n=400, defect=0):
    xy = np.random.default_rng(0).uniform(41, 59, (n, 2))
    code = np.zeros(n, np.int8)
    code[:defect] = OVER
    dev = SimpleNamespace(vertices_O=np.column_stack([xy, np.full(n, measured_mm)]),
                          foot_O=np.column_stack([xy, np.full(n, reference_mm)]),
                          class_code=code, outside_mm=np.zeros(n),
                          normals_O=np.tile([0.0, 0.0, 1.0], (n, 1)), n_vertices=n)
    return SimpleNamespace(layer=0, deviation=dev)


class SeenTop:
    def __init__(self, ratio):
        self.ratio, self.excluded, self.fused = ratio, None, None

    def estimate(self, defect_xy_O=None, fused=None):
        self.excluded, self.fused = defect_xy_O, fused
        return self.ratio, 500


def test_recalibration_replaces_the_lagging_fused_estimate():
    # the fused first layer reads 0.90 of the reference, the top seen again 0.94
    fit = ProcessFit()
    assert fit.calibrating
    scale, rescale, _ = fit.update(calibration_layer(0.72, 0.8, defect=7))
    assert scale == pytest.approx(0.90) and rescale == pytest.approx(0.90)
    assert not fit.calibrating
    top = SeenTop(0.94)
    scale, rescale, plume = fit.recalibrate(top)
    assert (scale, rescale, plume) == (pytest.approx(0.94), pytest.approx(0.94), 1.0)
    assert top.excluded.shape == (7, 2)  # the flagged vertices' xy
    entry = fit.layers[0]
    assert entry["estimate"] == pytest.approx(0.94)
    assert entry["fused_estimate"] == pytest.approx(0.9)
    assert entry["next_scale"] == fit.scale == pytest.approx(0.94)
    assert entry["reobserved_cells"] == 500
    assert fit.recalibrate(SeenTop(1.2)) is None  # only once, at the calibration
    # the next layer grows 0.8 mm at 0.94: measured 0.72 + 0.752 on a reference 0.752 + 0.752
    fit.update(calibration_layer(0.72 + 0.752, 0.8 * 0.94 + 0.752))
    assert fit.layers[1]["estimate"] == pytest.approx(0.94)  # the fused lag cancels
    assert fit.findings()[0].startswith("deposition efficiency 6 % below nominal")


def test_without_enough_seen_the_fused_calibration_stays():
    fit = ProcessFit()
    fit.update(calibration_layer(0.72, 0.8))
    assert fit.recalibrate(SeenTop(None)) is None
    assert fit.scale == pytest.approx(0.9) and fit.layers[0]["reobserved_cells"] == 500
    assert "fused_estimate" not in fit.layers[0]


def test_the_scale_is_read_where_the_plume_width_does_not_matter():
    # the cell deposits 18 % above nominal with a plume 15 % wider than modelled: near the
    # pad's edges its finished top is lower than the reference's by the plume, not the scale
    from scipy.ndimage import gaussian_filter

    c = (np.arange(320) + 0.5) * CELL_MM
    x, y = np.meshgrid(c, c)
    pad = 0.8 * ((np.abs(x - 40) <= 8) & (np.abs(y - 40) <= 8))
    sigma = 2.0

    def deposit(s):
        return gaussian_filter(pad, s / CELL_MM, mode="constant")

    truth = 1.18 * deposit(1.15 * sigma)
    seen = {}
    for plume_sigma in (sigma, 0.0):  # the model's plume width known, or not
        close = ReferenceMap(deposit(sigma), CELL_MM, 0, 10.0, plume_sigma_mm=plume_sigma)
        top = ReobservedTop(close, 10.0, 15.0)
        i, j = np.nonzero(top.plateau)
        xy = np.column_stack([(j + 0.5) * CELL_MM, (i + 0.5) * CELL_MM])
        top.observe(np.column_stack([xy, truth[i, j]]), 11.0, close.heights_mm)
        seen[plume_sigma] = top.estimate()
    ratio, cells = seen[sigma]
    assert ratio == pytest.approx(1.18, abs=0.01)
    assert MIN_CELLS <= cells < seen[0.0][1]  # the plateau's flat middle only
    assert seen[0.0][0] < 1.16  # the whole plateau reads the scale low


def test_cells_that_changed_since_the_close_are_left_out():
    # a dent cut as the next layer starts lowers part of the finished top the profilers see
    # again; the fused layer never had it, so those cells are not the layer's final surface
    from dm2.process.reobserved_top import CHANGED_MM, changed_since_close

    rng = np.random.default_rng(7)
    close = pad_map()
    top = ReobservedTop(close, since_s=10.0, until_s=15.0)
    plateau = grid_xy(41, 59, 41, 49)  # 72 x 32 cells
    seen = np.full(len(plateau), 0.8 * 1.06) + rng.normal(0.0, 0.01, len(plateau))
    dent = np.hypot(*(plateau - [45.0, 45.0]).T) < 2.0
    seen[dent] -= 0.4
    top.observe(np.column_stack([plateau, seen]), 11.0, close.heights_mm.copy())
    # the fused layer: the same top 0.03 mm lower (its lag), one vertex per cell
    fused = (plateau, np.full(len(plateau), 0.8 * 1.06 - 0.03))
    ratio, cells = top.estimate(fused=fused)
    assert cells == 72 * 32 - dent.sum() and dent.sum() > 150
    assert ratio == pytest.approx(1.06, abs=0.01 / 0.8)
    assert top.estimate()[1] == 72 * 32  # without the fused layer: every cell counts
    # the rule alone: only cells off the median difference by more than CHANGED_MM (or four
    # robust spreads) change; no fused vertex within reach keeps a cell
    xy = np.column_stack([np.arange(23.0), np.zeros(23)])
    seen_mm = 1.03 + rng.normal(0.0, 0.01, 23)
    seen_mm[[5, 9]] += [-CHANGED_MM - 0.05, CHANGED_MM + 0.05]
    seen_mm[22] = 5.0  # its cell has no fused vertex within reach
    flags = changed_since_close(xy, seen_mm, xy[:22], np.full(22, 1.0))
    assert np.flatnonzero(flags).tolist() == [5, 9]
