"""The closed loop's bench score (dm2.bench.intent): a known patch off the intended top gives
its area, volume beyond the tolerance, max deviation and no top height error."""

import numpy as np
import pytest

from dm2.bench.intent import score_top
from dm2.core.messages import Toolpath


def _raster():
    """Layer 0: infill lines along x from 10 to 40 mm at y = 10, 12, ..., 30 (spacing 2)."""
    pts = []
    for j, y in enumerate(np.arange(10.0, 30.1, 2.0)):
        xs = (10.0, 40.0) if j % 2 == 0 else (40.0, 10.0)
        pts += [(xs[0], y), (xs[1], y)]
    p = np.c_[np.array(pts), np.zeros(len(pts))]
    n = len(p)
    return Toolpath(p, np.tile([0.0, 0.0, -1.0], (n, 1)), np.full(n, 30.0), np.zeros(n, np.int8),
                    np.zeros(n, np.int32), np.ones(n, bool), np.ones(n))


def test_a_patch_over_the_intent_is_scored_with_its_size():
    x, y = np.meshgrid(np.arange(0.25, 50.0, 0.5), np.arange(0.25, 40.0, 0.5))
    z = np.full_like(x, 0.8)
    patch = (x > 20.0) & (x < 24.0) & (y > 18.0) & (y < 22.0)  # 4 x 4 mm, 0.7 mm over
    z[patch] += 0.7
    z[(x < 9.0) | (y < 9.0)] = 0.0  # the bare plate outside the footprint
    s = score_top(np.c_[x.ravel(), y.ravel(), z.ravel()], _raster(), 0, 0.8, 2.0, 0.4)
    assert s["out_of_tolerance_mm2"] == pytest.approx(16.0)
    assert s["out_of_tolerance_mm3"] == pytest.approx(16.0 * 0.3)
    assert s["max_abs_deviation_mm"] == pytest.approx(0.7)
    assert s["top_error_mm"] == pytest.approx(0.0)
    # the footprint: 30 x 20 mm of infill plus a half spacing each side, less 2 mm of edge
    assert s["footprint_mm2"] == pytest.approx((30.0 + 2.0 - 4.0) * (20.0 + 2.0 - 4.0), rel=0.08)


def test_layers_to_recover():
    from dm2.cli.bench_closed_loop import layers_to_recover

    def layers(areas):
        return [{"out_of_tolerance_mm2": a, "footprint_mm2": 100.0} for a in areas]

    assert layers_to_recover(layers([0.0, 3.0, 4.9])) == 0  # never above 5 %
    assert layers_to_recover(layers([0.0, 40.0, 20.0, 2.0, 1.0])) == 2  # out at 1, back at 3
    assert layers_to_recover(layers([0.0, 40.0, 60.0])) is None  # not back by the last layer
