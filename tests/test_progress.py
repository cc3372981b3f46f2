"""Nominal process time from path progress (the near-net reference's clock)."""

import numpy as np
import pytest

from dm2.core.messages import Toolpath
from dm2.reference.path_clock import ToolpathProgress


def make_toolpath(points, speeds):
    n = len(points)
    return Toolpath(np.asarray(points, float), np.tile([0, 0, -1.0], (n, 1)),
                    np.asarray(speeds, float), np.zeros(n), np.zeros(n), np.ones(n, bool),
                    np.ones(n))


def walk(points, step_mm):
    """Spots every ``step_mm`` along a polyline (an executed motion at any speed profile)."""
    out = [points[0]]
    for a, b in zip(points[:-1], points[1:], strict=True):
        n = max(int(np.ceil(np.linalg.norm(b - a) / step_mm)), 1)
        out.extend(a + (b - a) * (k / n) for k in range(1, n + 1))
    return np.array(out)


def test_nominal_time_is_programmed_time_whatever_the_real_timing():
    pts = np.array([[0, 0, 0], [30, 0, 0], [30, 2, 0], [0, 2, 0.0]])
    tp = make_toolpath(pts, [30, 30, 50, 15])
    expected = 30 / 30 + 2 / 50 + 30 / 15
    spots = walk(pts, 0.07)
    # the robot dwells 200 samples at the first reversal and jitters 0.02 mm while it waits
    rng = np.random.default_rng(3)
    k = int(np.argmin(np.linalg.norm(spots - pts[1], axis=1)))
    dwell = pts[1] + rng.normal(0, 0.02, (200, 3))
    spots = np.vstack([spots[:k + 1], dwell, spots[k + 1:]])
    prog = ToolpathProgress(tp)
    dt = np.concatenate([prog.advance(chunk) for chunk in np.array_split(spots, 7)])
    assert dt.sum() == pytest.approx(expected, abs=0.1 / 15)  # one resampling step
    assert dt[k + 1:k + 201].sum() < 0.1 / 30 * 3  # the dwell adds (almost) nothing
    assert prog.relocks == 0


def test_crossing_itself_never_jumps_ahead():
    # a square loop crossed by a later stroke through its middle at the same height
    pts = np.array([[0, 0, 0], [20, 0, 0], [20, 20, 0], [0, 20, 0], [0, 10, 0], [20, 10, 0.0]])
    tp = make_toolpath(pts, [20] * 6)
    prog = ToolpathProgress(tp)
    dt = prog.advance(walk(pts, 0.05))
    assert dt.sum() == pytest.approx(90 / 20, abs=0.01)  # 20 + 20 + 20 + 10 + 20 mm
    assert np.all(dt < 0.05)  # no sample is worth more than a short stretch


def test_leaving_the_path_relocks_without_adding_time():
    pts = np.array([[0, 0, 0], [40, 0, 0.0]])
    tp = make_toolpath(pts, [20, 20])
    prog = ToolpathProgress(tp)
    on1 = walk(np.array([[0, 0, 0], [10, 0, 0.0]]), 0.1)
    off = np.array([[20, 30, 0.0], [30, 30, 0.0]])  # an approach move far from the path
    on2 = walk(np.array([[30, 0, 0], [40, 0, 0.0]]), 0.1)
    dt = prog.advance(np.vstack([on1, off, on2]))
    assert prog.relocks == 1
    assert dt.sum() == pytest.approx(20 / 20, abs=0.02)  # 10 mm + 10 mm at 20 mm/s


def test_executed_clock_keeps_slow_motion_and_drops_standing_still():
    pts = np.array([[0, 0, 0], [30, 0, 0.0]])
    tp = make_toolpath(pts, [30, 30])
    # accelerate from rest at 500 mm/s^2 to 30 mm/s, then stand still 0.8 s, then cruise
    dt = 0.004
    x, v, xs = 0.0, 0.0, []
    while x < 10.0:
        v = min(v + 500 * dt, 30.0)
        x += v * dt
        xs.append(x)
    moving_s = len(xs) * dt
    xs += [xs[-1]] * 200  # 0.8 s dwell
    while xs[-1] < 29.0:
        xs.append(xs[-1] + 30 * dt)
    spots = np.column_stack([xs, np.zeros(len(xs)), np.zeros(len(xs))])
    elapsed = np.full(len(xs), dt)
    prog = ToolpathProgress(tp)
    nominal = prog.advance(spots, elapsed, dwell_speed_mm_s=1.0)
    cruise_s = (len(xs) - 200 - int(round(moving_s / dt))) * dt
    # slow motion (acceleration) counts in full; of the 0.8 s dwell at most one resampling
    # step (0.1 mm) over the dwell speed (1 mm/s) is credited
    assert moving_s + cruise_s - 2 * dt <= nominal.sum() <= moving_s + cruise_s + 0.1 + 2 * dt
    assert nominal[int(round(moving_s / dt)) + 1:int(round(moving_s / dt)) + 200].sum() == 0.0
    # the programmed clock would only count distance over 30 mm/s
    prog2 = ToolpathProgress(tp)
    assert prog2.advance(spots).sum() == pytest.approx((xs[-1] - xs[0]) / 30.0, abs=0.01)
