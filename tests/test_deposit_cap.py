"""Deposition buries what the profilers saw: the weights around the spray axis are capped as
the spot passes (dm2.fusion.tsdf.deposit), and the comparison is against the reference as the
profilers last saw each column (dm2.pipeline.seen_reference)."""

from __future__ import annotations

import numpy as np
import pytest
from test_tsdf import _plane_rays, _zero_crossing

from dm2.fusion.tsdf.field import SparseTSDF
from dm2.pipeline.seen_reference import SeenReference
from dm2.reference.height_map import ReferenceMap


def _observe(tsdf, z, rng, passes):
    for _ in range(passes):  # inactive rays: the history accumulates up to the weight cap
        o, p = _plane_rays(20_000, z, rng, tilt=(0.0, 0.0, 80.0))
        tsdf.integrate(o, p)


def test_a_pass_of_the_spot_lets_the_next_profiles_decide_the_surface_only_there():
    rng = np.random.default_rng(5)
    tsdf = SparseTSDF(0.5, 1.5, weight_cap=4.0)
    _observe(tsdf, 0.0, rng, 20)  # long history of the old surface, 1 mm below the new one
    n = tsdf.cap_weights_near_axis(np.array([20.0, 20.0, 0.0]), np.array([0.0, 0.0, -1.0]),
                                   radius_mm=6.0, half_length_mm=6.0, weight_cap=1.0)
    assert n > 0
    _, w = tsdf.sample(np.array([[20.1, 20.1, 0.25], [35.1, 35.1, 0.25]]))
    assert w[0] == 1.0 and w[1] > 10.0  # capped within 6 mm of the axis only
    _observe(tsdf, 1.0, rng, 5)  # a few passes of the profilers over the new deposit
    assert _zero_crossing(tsdf, 20.2, 20.2) == pytest.approx(1.0, abs=0.1)
    assert _zero_crossing(tsdf, 35.2, 35.2) < 0.5  # outside the spray: the history stays


def test_growth_after_the_last_observation_is_the_unseen_part():
    cell = 0.25
    live = np.zeros((40, 40))
    live[:, :20] = 0.8  # the left half sprayed once
    seen = SeenReference(live.shape, cell, radius_mm=0.0)
    xy = np.column_stack([np.full(80, 2.0), np.linspace(0.05, 9.95, 80), np.full(80, 0.8)])
    seen.observe(xy, 1.0, live)  # a profile line
    live[:, :20] += 0.5  # sprayed again: nobody has looked since
    ref = ReferenceMap(live.copy(), cell)
    unseen = seen.unseen(ref)
    col = int(2.0 / cell)
    assert np.allclose(unseen.heights_mm[:, col], 0.5)  # the column the profile saw
    assert np.count_nonzero(unseen.heights_mm) == 40  # and nothing else (never observed)
    for _ in range(3):  # later layers: the plume's tail lands there, no profile sees it
        live[:, :20] += 0.2
    assert np.allclose(seen.unseen(ReferenceMap(live.copy(), cell)).heights_mm[:, col], 1.1)
    seen.observe(xy, 9.0, live)  # seen again: nothing unseen left
    assert not seen.unseen(ReferenceMap(live.copy(), cell)).heights_mm.any()


def test_observing_marks_every_cell_within_reach_of_each_point_as_a_plain_loop_does():
    rng = np.random.default_rng(12)
    cell, shape = 0.25, (60, 80)
    live = rng.random(shape)
    seen = SeenReference(shape, cell, radius_mm=0.25)  # one cell of reach
    # a profile line (several points per cell, so consecutive points share cells), points
    # off the plate and NaN
    t = np.linspace(0.0, 1.0, 400)
    xyz = np.column_stack([-1.0 + 22.0 * t, 2.0 + 12.0 * t ** 2, rng.normal(5.0, 1.0, 400)])
    xyz[50] = np.nan
    seen.surface_mm[:] = -3.0  # an earlier observation's surface (another stamp)
    seen.observe(xyz, 3.0, live)
    want = np.zeros(shape, bool)
    lowest = np.full(shape, np.inf)
    last = None
    for x, y, z in xyz:
        if not (x >= 0 and y >= 0 and x / cell < shape[1] and y / cell < shape[0]):
            continue
        i, j = int(y // cell), int(x // cell)
        if (i, j) == last:  # a point in the cell of the point before writes nothing new
            continue
        last = (i, j)
        want[max(i - 1, 0):i + 2, max(j - 1, 0):j + 2] = True
        box = lowest[max(i - 1, 0):i + 2, max(j - 1, 0):j + 2]
        np.minimum(box, z, out=box)
    assert np.array_equal(np.isfinite(seen.stamp_s), want)
    assert np.all(seen.stamp_s[want] == 3.0)
    assert np.array_equal(seen.heights_mm[want], live[want])
    # the seen surface: the lowest marking point of this stamp, the earlier one replaced
    assert np.array_equal(seen.surface_mm[want], lowest[want])
    assert np.all(seen.surface_mm[~want] == -3.0)
    # expected now: that height plus the reference's growth since (none never seen)
    grown, snap = seen.since_seen(ReferenceMap(live + 0.5, cell))
    seen.surface_mm[:] = 0.0  # the snapshot is a copy
    assert np.allclose(snap.heights_mm[want], lowest[want] + 0.5)
    assert np.all(snap.heights_mm[~want] == -np.inf)
    assert np.allclose(grown.heights_mm[want], 0.5) and not grown.heights_mm[~want].any()
