"""The real-time window's reference curvature equals the layer analysis's (scipy) statement."""

import numpy as np

from dm2.defects.realtime_curvature import window_mean_curvature
from dm2.reference.height_map import ReferenceMap


def test_window_curvature_equals_the_whole_map_statement():
    rng = np.random.default_rng(7)
    cell, v = 0.25, 0.5
    n = 480  # a 120 mm plate
    c = (np.arange(n) + 0.5) * cell
    xx, yy = np.meshgrid(c, c)
    # a pad with rounded edges, a dome and a little noise: curvature of both signs
    h = 2.0 / (1 + np.exp(-(20 - np.maximum(abs(xx - 60), abs(yy - 60))) / 0.8))
    h += 1.5 * np.exp(-((xx - 55) ** 2 + (yy - 62) ** 2) / 8.0) + rng.normal(0, 0.01, h.shape)
    ref = ReferenceMap(h, cell)
    grid = ref.resampled(v)  # the reference at the voxel columns, as the layer compares it
    nxm = nym = 240
    for i0, j0 in [(60, 70), (100, 110), (0, 0), (230, 5)]:
        i1, j1 = min(i0 + 24, nxm), min(j0 + 24, nym)
        got = window_mean_curvature(h, cell, i0, j0, i1, j1, v, nxm, nym)
        ys, xs = np.mgrid[j0:j1, i0:i1]
        xy = np.column_stack([(xs.ravel() + 0.5) * v, (ys.ravel() + 0.5) * v])
        want = grid.mean_curvature_at(xy).reshape(got.shape)
        interior = (i0 >= 8) and (j0 >= 8) and (i1 <= nxm - 8) and (j1 <= nym - 8)
        if interior:  # (near the plate's border the window's margin is cut)
            assert np.allclose(got, want, rtol=0, atol=1e-9)
            assert np.abs(got).max() > 0.05  # the pad's edge and the dome are curved
        else:
            assert got.shape == (j1 - j0, i1 - i0) and np.abs(got).max() < 0.01  # flat plate


def test_window_laplacian_gives_the_layer_analysis_plume_term():
    # a Gaussian ridge (one straight pass): the real-time plume term sigma^2 * laplacian equals
    # the layer analysis's ReferenceMap.plume_sensitivity_at (another stencil: within 3 %)
    from dm2.defects.realtime_curvature import window_curvatures

    cell, v, sigma = 0.25, 0.5, 2.95
    c = (np.arange(480) + 0.5) * cell
    xx, _ = np.meshgrid(c, c)
    h = 6.0 / (np.sqrt(2 * np.pi) * sigma) * np.exp(-(xx - 60.0) ** 2 / (2 * sigma ** 2))
    grid = ReferenceMap(h, cell, plume_sigma_mm=sigma).resampled(v)
    i0, j0, i1, j1 = 100, 110, 140, 130  # x 50..70 mm across the ridge
    _, lap = window_curvatures(h, cell, i0, j0, i1, j1, v, 240, 240)
    ys, xs = np.mgrid[j0:j1, i0:i1]
    xy = np.column_stack([(xs.ravel() + 0.5) * v, (ys.ravel() + 0.5) * v])
    want = grid.plume_sensitivity_at(xy).reshape(lap.shape)
    got = sigma ** 2 * lap
    assert np.abs(got - want).max() < 0.03 * np.abs(want).max()
    assert got[:, 20].max() < 0 and got[:, 0].min() > 0  # crest down, flanks (x 50 mm) up
