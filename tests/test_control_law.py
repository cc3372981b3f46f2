"""The correction law (dm2.control): known errors give the predicted speed factors, and the
bounds, the rate limit and the acceleration limit hold."""

import numpy as np
import pytest

from dm2.control import TopMap, correct_layer, measured_top
from dm2.control.law import accel_limit
from dm2.core.config import ControlConfig
from dm2.core.messages import Toolpath

LAYER_MM = 0.8


def _toolpath(xs=(0.0, 20.0, 40.0, 60.0), speed=30.0):
    """Layer 0 at z 0 and layer 1 at z 0.8, each one spraying line along x at y 10."""
    xs = np.asarray(xs)
    pos = np.concatenate([np.c_[xs, np.full_like(xs, 10.0), np.full_like(xs, z)]
                          for z in (0.0, LAYER_MM)])
    n = len(pos)
    axis = np.tile([0.0, 0.0, -1.0], (n, 1))
    layer = np.repeat([0, 1], len(xs))
    spray = np.ones(n, bool)
    spray[[0, len(xs)]] = False  # each layer's first move is the approach
    return Toolpath(pos, axis, np.full(n, speed), np.zeros(n, np.int8), layer, spray,
                    np.ones(n))


def _top(short_mm=0.0, x_range=(20.0, 40.0)):
    """A measured top at 0.8 mm (layer 0 as planned), ``short_mm`` lower over ``x_range``."""
    x = np.arange(0.5, 70.0, 1.0)
    z = np.full((20, len(x)), LAYER_MM)
    z[:, (x >= x_range[0]) & (x <= x_range[1])] -= short_mm
    return TopMap(z, np.array([0.0, 0.0]), 1.0)


def test_half_a_millimetre_short_over_one_segment_gives_the_predicted_factor():
    cfg = ControlConfig(rate_per_layer=1.0)
    tp = _toolpath()
    out, corr = correct_layer(tp, 1, _top(0.5), cfg, LAYER_MM)
    predicted = LAYER_MM / (LAYER_MM + cfg.gain * 0.5)  # 0.6667: slow down, lay 1.2 mm
    # the top is read over the plume's width (1.5 mm sigma): 10 mm off, the step is not seen
    np.testing.assert_allclose(corr.error_mm[1:], [0.0, 0.5, 0.0], atol=1e-9)
    np.testing.assert_allclose(corr.factor, [1.0, 1.0, predicted, 1.0], atol=1e-4)
    np.testing.assert_allclose(out.speed_mm_s[5:], [30.0, 30.0 * predicted, 30.0], atol=5e-4)
    # only that segment's speed changed; the geometry, layer 0 and the rest as programmed
    np.testing.assert_array_equal(out.position_O, tp.position_O)
    np.testing.assert_array_equal(out.axis_O, tp.axis_O)
    np.testing.assert_array_equal(out.zone_mm, tp.zone_mm)
    changed = np.flatnonzero(np.abs(out.speed_mm_s - tp.speed_mm_s) > 1e-6)
    np.testing.assert_array_equal(changed, [6])
    # the same error above the plan speeds the nozzle up by the law
    _, over = correct_layer(tp, 1, _top(-0.25), cfg, LAYER_MM)
    assert over.factor[2] == pytest.approx(LAYER_MM / (LAYER_MM - cfg.gain * 0.25), abs=1e-4)


def test_bounds_hold():
    cfg = ControlConfig(rate_per_layer=5.0)
    tp = _toolpath()
    _, short = correct_layer(tp, 1, _top(3.0), cfg, LAYER_MM)
    assert short.factor[2] == cfg.min_speed_factor
    _, over = correct_layer(tp, 1, _top(-3.0), cfg, LAYER_MM)  # would lay nothing: inf
    assert over.factor[2] == cfg.max_speed_factor
    capped = ControlConfig(rate_per_layer=5.0, max_speed_mm_s=40.0)
    _, over = correct_layer(tp, 1, _top(-3.0), capped, LAYER_MM)
    assert over.speed_mm_s[2] == pytest.approx(40.0)


def test_the_rate_limit_holds_layer_to_layer():
    cfg = ControlConfig()  # 0.2 per layer
    tp = _toolpath()
    target = LAYER_MM / (LAYER_MM + cfg.gain * 0.5)
    _, first = correct_layer(tp, 1, _top(0.5), cfg, LAYER_MM)
    assert first.factor[2] == pytest.approx(1.0 - cfg.rate_per_layer, abs=1e-4)
    _, second = correct_layer(tp, 1, _top(0.5), cfg, LAYER_MM, previous=first)
    assert second.factor[2] == pytest.approx(max(target, 1.0 - 2 * cfg.rate_per_layer), abs=1e-4)
    # the part now stands 0.5 mm over: the factor climbs back by the rate at most
    _, third = correct_layer(tp, 1, _top(-0.5), cfg, LAYER_MM, previous=second)
    assert third.factor[2] == pytest.approx(second.factor[2] + cfg.rate_per_layer, abs=1e-4)


def test_unmeasured_segments_stay_programmed():
    z = _top(0.5).z_mm.copy()
    z[:, :] = np.nan
    _, corr = correct_layer(_toolpath(), 1, TopMap(z, np.zeros(2), 1.0), ControlConfig(),
                            LAYER_MM)
    assert np.all(corr.factor == 1.0) and np.all(np.isnan(corr.error_mm[1:]))


def test_accel_limit_known_values_and_constraints():
    v = accel_limit(np.array([30.0, 60.0, 30.0]), np.array([1.0, 1.0, 1.0]),
                    np.array([True, False, False]), 500.0)
    np.testing.assert_allclose(v, [30.0, np.sqrt(900.0 + 500.0), 30.0])
    rng = np.random.default_rng(7)
    for _ in range(20):
        n = 50
        v0 = rng.uniform(18.0, 48.0, n)
        ln = rng.uniform(0.2, 3.0, n)
        start = rng.random(n) < 0.1
        start[0] = True
        v = accel_limit(v0, ln, start, 300.0)
        assert np.all(v <= v0 + 1e-12) and np.all(v >= v0.min() - 1e-12)
        tied = ~start[1:]
        assert np.all((v[1:] ** 2 - v[:-1] ** 2)[tied] <= 300.0 * ln[1:][tied] + 1e-9)
        assert np.all((v[:-1] ** 2 - v[1:] ** 2)[tied] <= 300.0 * ln[:-1][tied] + 1e-9)


def test_smoothing_respects_the_robots_acceleration_in_a_corrected_layer():
    xs = np.arange(0.0, 41.0, 1.0)  # 1 mm moves: 18 -> 30 mm/s takes ~3 mm at 200 mm/s^2
    cfg = ControlConfig(rate_per_layer=1.0, accel_mm_s2=200.0)
    tp = _toolpath(xs)
    _, corr = correct_layer(tp, 1, _top(3.0), cfg, LAYER_MM)
    v, ln = corr.speed_mm_s, np.r_[0.0, np.diff(xs)]
    slack = 4 * 30.0 * 5e-4  # v^2 of two speeds each rounded to 0.001 mm/s
    assert np.all(np.diff(v[1:] ** 2) <= 200.0 * ln[2:] + slack)
    assert np.all(-np.diff(v[1:] ** 2) <= 200.0 * ln[1:-1] + slack)
    assert np.all(corr.factor[1:] >= cfg.min_speed_factor - 1e-9)
    assert corr.factor[25] == pytest.approx(cfg.min_speed_factor)  # inside: the full slowdown
    assert corr.factor[10] == 1.0  # far before the short stretch: as programmed
    assert 0.6 < corr.factor[18] < 0.9  # the ramp down ends where the short stretch begins


def test_measured_top_keeps_confident_up_facing_vertices():
    verts = np.array([[0.5, 0.5, 1.0], [0.6, 0.4, 1.2], [0.5, 0.6, 5.0], [0.4, 0.5, 7.0],
                      [1.5, 0.5, 2.0]])
    normals = np.array([[0, 0, 1.0], [0, 0, 1.0], [1.0, 0, 0], [0, 0, 1.0], [0, 0, 1.0]])
    weight = np.array([2.0, 2.0, 2.0, 0.5, 2.0])  # a flank at 5 mm, a weak vertex at 7 mm
    top = measured_top(verts, normals, weight, 1.0, min_weight=1.0, bounds_O=(0, 0, 3, 1))
    np.testing.assert_allclose(top.z_mm, [[1.2, 2.0, np.nan]])
    np.testing.assert_allclose(top.sample(np.array([[0.5, 0.5], [2.5, 0.5], [9.0, 0.5]])),
                               [1.2, np.nan, np.nan])
