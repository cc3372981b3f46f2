"""Near-net reference: analytic Gaussian integral, mass balance, spray-angle efficiency."""

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from dm2.core.config import MonitorConfig, ProcessConfig
from dm2.core.frames import invert, make_T
from dm2.core.messages import Calibration, LayerMark, RobotState
from dm2.reference.height_map import ReferenceMap
from dm2.reference.model import (
    NearNetReference,
    deposition_efficiency,
    plume_sigma_mm,
    volume_rate_mm3_s,
)

SPOT_B = np.array([1300.0, 0.0, 870.0])  # nozzle exit at z 900, pointing down, standoff 30
T_B_N = make_T(Rotation.from_euler("x", 180, degrees=True), [1300.0, 0.0, 900.0])
T_F_O = make_T(Rotation.from_euler("z", 30, degrees=True), [-60.0, -60.0, 150.0])
CAL = Calibration({}, T_F_O, T_B_N)


def flange_poses(points_O, axes_O=None):
    """Flange poses putting each ``points_O`` on the spot with ``axes_O`` along +z_N."""
    out = []
    for k, p in enumerate(points_O):
        a = np.array([0.0, 0.0, -1.0]) if axes_O is None else axes_O[k]
        R_B_O, _ = Rotation.align_vectors([[0.0, 0.0, -1.0]], [a])  # R_B_O @ a = z_N
        T_B_O = make_T(R_B_O, SPOT_B - R_B_O.apply(p))
        out.append(T_B_O @ invert(T_F_O))
    return np.array(out)


def straight_pass(proc, v=30.0, y=60.125, rate_hz=250.0, axis=None):
    ts = np.arange(0.0, 100.0 / v + 1e-9, 1.0 / rate_hz)
    pts = np.column_stack([10.0 + v * ts, np.full_like(ts, y), np.zeros_like(ts)])
    axes = None if axis is None else np.tile(axis, (len(ts), 1))
    return ts, flange_poses(pts, axes)


def test_spot_in_O_recovers_the_toolpath_point():
    ref = NearNetReference(ProcessConfig(), MonitorConfig(), CAL)
    p = np.array([[12.0, 80.0, 1.6]])
    a = np.array([[np.sin(0.6), 0.0, -np.cos(0.6)]])
    spot, axis = ref.spot_O(flange_poses(p, a))
    assert np.allclose(spot, p, atol=1e-9) and np.allclose(axis, a, atol=1e-12)


@pytest.mark.parametrize("sigma,v,rate", [(None, 30.0, 250.0), (1.5, 12.0, 250.0),
                                          (3.0, 50.0, 20.0)])
def test_straight_pass_matches_analytic_gaussian_integral(sigma, v, rate):
    proc = ProcessConfig(plume_sigma_mm=sigma)  # the flat-plate closed form: angle from +z
    ref = NearNetReference(proc, MonitorConfig(), CAL, cell_mm=0.25, angle_from_surface=False)
    ts, T = straight_pass(proc, v=v, rate_hz=rate)
    ref.add_states(ts, T)
    s = plume_sigma_mm(proc)
    peak = volume_rate_mm3_s(proc) * proc.deposition_efficiency / (math.sqrt(2 * math.pi) * s * v)
    m = ref.snapshot()
    assert m.height_at([[60.0, 60.125]])[0] == pytest.approx(peak, rel=0.02)
    # cross profile is the Gaussian of that sigma
    assert m.height_at([[60.0, 60.125 + s]])[0] == pytest.approx(peak * math.exp(-0.5), rel=0.02)
    # mass balance: all powder times efficiency landed on the plate
    expected = volume_rate_mm3_s(proc) * proc.deposition_efficiency * ts[-1]
    assert ref.deposited_mm3 == pytest.approx(expected, rel=0.005)
    assert m.heights_mm.sum() * 0.25 ** 2 == pytest.approx(expected, rel=0.005)


def test_default_sigma_formula_and_efficiency_falloff():
    proc = ProcessConfig()
    r = 6.55 / 2 + 30.0 * math.tan(math.radians(5.0))
    assert plume_sigma_mm(proc) == pytest.approx(r / 2) == pytest.approx(2.95, abs=0.01)
    z = deposition_efficiency(np.radians([0.0, 35.0, 75.0, 80.0]), proc)
    assert z[0] == pytest.approx(0.5)
    assert z[1] == pytest.approx(0.5 * math.cos(0.5 * math.pi * (35 / 75) ** 2) ** 2)
    assert z[2] == pytest.approx(0.0, abs=1e-12) and z[3] == 0.0


def test_tilted_edge_spray_deposits_zeta_of_its_angle():
    proc = ProcessConfig()
    ref = NearNetReference(proc, MonitorConfig(), CAL, angle_from_surface=False)
    alpha = math.radians(35.0)
    ts, T = straight_pass(proc, axis=np.array([0.0, math.sin(alpha), -math.cos(alpha)]))
    ref.add_states(ts, T)
    zeta = deposition_efficiency(alpha, proc)
    assert ref.deposited_mm3 == pytest.approx(volume_rate_mm3_s(proc) * zeta * ts[-1], rel=0.01)
    # the footprint is stretched across the pass by 1 / cos(alpha): lower, wider ridge
    m = ref.snapshot()
    ridge = m.heights_mm[:, 240]
    y = (np.arange(len(ridge)) + 0.5) * 0.25
    centre = float((ridge * y).sum() / ridge.sum())
    spread = math.sqrt(float((ridge * (y - centre) ** 2).sum() / ridge.sum()))
    assert centre == pytest.approx(60.125, abs=0.05)
    assert spread == pytest.approx(plume_sigma_mm(proc) / math.cos(alpha), rel=0.02)


def test_feed_messages_snapshots_layers_and_skips_gaps():
    proc = ProcessConfig()
    ref = NearNetReference(proc, MonitorConfig(), CAL)
    ts, T = straight_pass(proc)
    half = len(ts) // 2
    for k in range(half):
        ref.feed(RobotState(ts[k], k, np.zeros(6), T[k]))
    done = ref.feed(LayerMark(ts[half], 1))
    assert isinstance(done, ReferenceMap) and done.layer == 0 and ref.layers[0] is done
    for k in range(half, len(ts)):
        ref.feed(RobotState(ts[k] + 5.0, k, np.zeros(6), T[k]))  # a 5 s hole in the stream
    rate = volume_rate_mm3_s(proc) * proc.deposition_efficiency
    assert ref.gaps_skipped == 1
    assert ref.deposited_mm3 == pytest.approx(rate * (ts[-1] - ts[1]), rel=0.01)
    assert done.heights_mm.sum() < ref.snapshot().heights_mm.sum()
    with pytest.raises(ValueError, match="backwards"):
        ref.add_states([0.0], T[:1])


def test_angle_from_surface_uses_the_local_slope():
    proc = ProcessConfig()
    slope = math.radians(20.0)
    ref = NearNetReference(proc, MonitorConfig(), CAL, angle_from_surface=True)
    x = (np.arange(ref.heights_mm.shape[1]) + 0.5) * ref.cell_mm
    ref.heights_mm[:] = 5.0 + math.tan(slope) * (x - 60.0)[None, :]  # a 20 degree ramp in x
    before = ref.heights_mm.sum()
    ts, T = straight_pass(proc, v=30.0)
    ts, T = ts[:100], T[:100]  # stay away from the plate border
    pts = ref.spot_O(T)[0]
    T = flange_poses(np.column_stack([pts[:, 1] * 0 + 60.0, 20.0 + 30.0 * ts, pts[:, 2]]))
    ref.add_states(ts, T)
    expected = volume_rate_mm3_s(proc) * deposition_efficiency(slope, proc) * ts[-1]
    assert ref.deposited_mm3 == pytest.approx(expected, rel=0.01)
    added = (ref.snapshot().heights_mm.sum() - before) * ref.cell_mm ** 2
    assert added == pytest.approx(expected, rel=0.01)


def test_layers_split_by_toolpath_without_marks():
    from dm2.core.messages import Toolpath

    proc = ProcessConfig()
    pts = np.array([[10.0, 40.0, 0.0], [110.0, 40.0, 0.0], [110.0, 80.0, 0.8],
                    [10.0, 80.0, 0.8]])
    tp = Toolpath(pts, np.tile([0.0, 0.0, -1.0], (4, 1)), np.full(4, 30.0), np.zeros(4),
                  [0, 0, 1, 1], np.ones(4, bool), np.zeros(4))
    ref = NearNetReference(proc, MonitorConfig(), CAL, toolpath=tp)
    ts = np.arange(0.0, 4.0, 1 / 250)
    first = np.column_stack([10 + 30 * ts, np.full_like(ts, 40.0), np.zeros_like(ts)])
    second = np.column_stack([110 - 30 * ts, np.full_like(ts, 80.0), np.full_like(ts, 0.8)])
    poses = flange_poses(np.vstack([first[ts <= 10 / 3], second[ts <= 10 / 3]]))
    stamps = np.concatenate([ts[ts <= 10 / 3], 10.0 + ts[ts <= 10 / 3]])
    done = [ref.feed(RobotState(t, k, np.zeros(6), T))
            for k, (t, T) in enumerate(zip(stamps, poses, strict=True))]
    maps = [m for m in done if m is not None]
    assert [m.layer for m in maps] == [0] and ref.layer == 1
    layer0 = maps[0]
    peak = volume_rate_mm3_s(proc) * 0.5 / (math.sqrt(2 * math.pi) * plume_sigma_mm(proc) * 30)
    assert layer0.height_at([[60.0, 40.0]])[0] == pytest.approx(peak, rel=0.02)
    assert layer0.height_at([[60.0, 80.0]])[0] < 1e-6
    assert ref.snapshot().height_at([[60.0, 80.0]])[0] == pytest.approx(peak, rel=0.02)


def test_tilted_spray_lands_where_its_axis_meets_a_lagging_surface():
    """A 35 degree edge spray programmed 2 mm above a flat surface lands 2 tan(35) further out."""
    proc = ProcessConfig()
    alpha = math.radians(35.0)
    axis = np.array([0.0, math.sin(alpha), -math.cos(alpha)])
    ref = NearNetReference(proc, MonitorConfig(), CAL, angle_from_surface=False)
    ts = np.arange(0.0, 100.0 / 30.0 + 1e-9, 1 / 250)
    pts = np.column_stack([10.0 + 30.0 * ts, np.full_like(ts, 60.125), np.full_like(ts, 2.0)])
    ref.add_states(ts, flange_poses(pts, np.tile(axis, (len(ts), 1))))
    ridge = ref.snapshot().heights_mm[:, 240]
    y = (np.arange(len(ridge)) + 0.5) * ref.cell_mm
    centre = float((ridge * y).sum() / ridge.sum())
    assert centre == pytest.approx(60.125 + 2.0 * math.tan(alpha), abs=0.05)
    # the same spray onto a surface 2 mm higher than programmed lands 2 tan(35) short of it
    ref = NearNetReference(proc, MonitorConfig(), CAL, angle_from_surface=False)
    ref.heights_mm[:] = 2.0
    ref.heights_written()
    pts[:, 2] = 0.0
    ref.add_states(ts, flange_poses(pts, np.tile(axis, (len(ts), 1))))
    ridge = ref.snapshot().heights_mm[:, 240] - 2.0
    centre = float((ridge * y).sum() / ridge.sum())
    assert centre == pytest.approx(60.125 - 2.0 * math.tan(alpha), abs=0.05)


def test_tilted_spray_onto_a_slope_follows_its_rays():
    """A 35 degree spray along a plane rising 0.5 mm/mm into the jet: each ray lands where it
    meets the plane, so the ridge is sigma / (cos a + s sin a) wide across the pass (a flat
    plate at the impact height would give sigma / cos a, a third wider), centred on the
    impact, and its volume is the powder's at the plane's spray angle (nothing is lost or
    made by the slope)."""
    proc = ProcessConfig()
    alpha, s = math.radians(35.0), 0.5
    axis = np.array([0.0, math.sin(alpha), -math.cos(alpha)])
    ref = NearNetReference(proc, MonitorConfig(), CAL)
    y = (np.arange(ref.heights_mm.shape[0]) + 0.5) * ref.cell_mm
    ref.heights_mm[:] = (20.0 + s * (y - 60.125))[:, None]
    ref.heights_written()
    before = ref.heights_mm.copy()
    ts = np.arange(0.0, 100.0 / 30.0 + 1e-9, 1 / 250)
    pts = np.column_stack([10.0 + 30.0 * ts, np.full_like(ts, 60.125), np.full_like(ts, 20.0)])
    ref.add_states(ts, flange_poses(pts, np.tile(axis, (len(ts), 1))))
    ridge = (ref.snapshot().heights_mm - before)[:, 240]
    centre = float((ridge * y).sum() / ridge.sum())
    spread = math.sqrt(float((ridge * (y - centre) ** 2).sum() / ridge.sum()))
    assert centre == pytest.approx(60.125, abs=0.05)
    expected = plume_sigma_mm(proc) / (math.cos(alpha) + s * math.sin(alpha))
    assert spread == pytest.approx(expected, rel=0.02)
    assert abs(spread - plume_sigma_mm(proc) / math.cos(alpha)) > 0.5  # not the flat plate's
    theta = math.acos((s * math.sin(alpha) + math.cos(alpha)) / math.sqrt(1.0 + s * s))
    zeta = deposition_efficiency(theta, proc)
    assert ref.deposited_mm3 == pytest.approx(volume_rate_mm3_s(proc) * zeta * ts[-1], rel=0.02)


def test_each_footprint_cell_sticks_at_its_own_spray_angle():
    """A vertical spray centred on the edge of a 50 degree flank: half the powder meets the
    flat top (zeta(0)), half the flank (zeta(50 deg)); the footprint's centre slope is no
    stand-in for either."""
    proc = ProcessConfig()
    slope = math.radians(50.0)
    ref = NearNetReference(proc, MonitorConfig(), CAL)
    x = (np.arange(ref.heights_mm.shape[1]) + 0.5) * ref.cell_mm
    ref.heights_mm[:] = (40.0 - math.tan(slope) * np.clip(x - 60.0, 0.0, None))[None, :]
    before = ref.heights_mm.sum()
    ts = np.arange(0.0, 40.0 / 30.0 + 1e-9, 1 / 250)
    pts = np.column_stack([np.full_like(ts, 60.0), 40.0 + 30.0 * ts, np.full_like(ts, 40.0)])
    ref.add_states(ts, flange_poses(pts))
    zeta = 0.5 * (deposition_efficiency(0.0, proc) + deposition_efficiency(slope, proc))
    expected = volume_rate_mm3_s(proc) * zeta * ts[-1]
    assert ref.deposited_mm3 == pytest.approx(expected, rel=0.02)
    added = (ref.snapshot().heights_mm.sum() - before) * ref.cell_mm ** 2
    assert added == pytest.approx(expected, rel=0.02)


def test_tilted_spray_past_a_wall_top_reaches_the_plate_below_on_every_ray():
    """A 35 degree spray aimed 5 mm inside the top edge of a 20 mm wall: the rays that pass
    the edge land on the plate 15-30 mm out. Exactly the cells whose surface point lies within
    the footprint's 4 sigmas of the axis receive powder, on the wall's top and on the plate
    (none is dropped by the kernel's search band, none outside it is touched)."""
    from dm2.reference import kernels as RK
    from dm2.reference.model import FOOTPRINT_SIGMAS

    alpha = math.radians(35.0)
    a = np.array([0.0, math.sin(alpha), -math.cos(alpha)])
    ref = NearNetReference(ProcessConfig(), MonitorConfig(), CAL, angle_from_surface=False)
    n = ref.heights_mm.shape[0]
    y = (np.arange(n) + 0.5) * ref.cell_mm
    ref.heights_mm[:] = np.where(y < 60.0, 20.0, 0.0)[:, None]
    ref.heights_written()
    before = ref.heights_mm.copy()
    p = np.array([60.0, 55.0, 20.0])
    hm = RK.HeightMap(ref.heights_mm, ref.cell_mm, ref._zmax, ref._scratch)
    RK.deposit_spot(hm, *p, *a, 0.05, ref._spray())
    got = ref.heights_mm > before

    xx, yy = np.meshgrid((np.arange(n) + 0.5) * ref.cell_mm, y)
    r = np.stack([xx - p[0], yy - p[1], before - p[2]], axis=-1)
    dist = np.sqrt(np.maximum((r * r).sum(-1) - (r @ a) ** 2, 0.0))
    radius = FOOTPRINT_SIGMAS * ref.sigma_mm
    clear = np.abs(dist - radius) > 0.01  # the impact is found to a sixty-fourth of a cell
    assert np.array_equal(got[clear], (dist <= radius)[clear])
    on_plate = got & (before == 0.0)
    assert on_plate.any() and yy[on_plate].max() > 55.0 + 20.0 * math.tan(alpha) + 10.0
    assert not (got & (yy < 40.0)).any()


@pytest.mark.parametrize("capacity", [16, None])
def test_feed_gives_the_same_reference_for_any_arrival_order_and_slicing(capacity, monkeypatch):
    """Robot states arriving out of order within the window and integrated in slices of any
    size build the reference bit for bit as in-order states integrated at once; a state older
    than the last integrated one is dropped. With a small first buffer the feed makes room
    (drops consumed rows, doubles) many times on the way."""
    from dm2.reference import feed as feed_module
    from dm2.reference.feed import ReferenceFeed

    if capacity is not None:
        monkeypatch.setattr(feed_module, "INITIAL_CAPACITY", capacity)

    proc = ProcessConfig()
    ts, poses = straight_pass(proc)
    ref_a = NearNetReference(proc, MonitorConfig(), CAL)
    feed_a = ReferenceFeed(ref_a)
    for t, T in zip(ts, poses, strict=True):
        feed_a.push(t, T)
    assert len(feed_a) == len(ts) and feed_a.flush()
    ref_b = NearNetReference(proc, MonitorConfig(), CAL)
    feed_b = ReferenceFeed(ref_b)
    rng = np.random.default_rng(3)
    order = np.argsort(np.arange(len(ts)) + rng.uniform(0, 6, len(ts)), kind="stable")
    assert not np.all(np.diff(order) > 0)  # some states arrive late
    pushed = 0
    for k in rng.integers(1, 40, 400):  # push a few, then integrate what is due in slices
        for i in order[pushed: pushed + k]:
            feed_b.push(ts[i], poses[i])
        pushed = min(pushed + k, len(ts))
        due = ts[order[:pushed]].min() if pushed < len(ts) else np.inf
        upto = min(due, ts[order[pushed:]].min()) if pushed < len(ts) else np.inf
        while not feed_b.flush(upto_s=np.nextafter(upto, -np.inf), max_states=int(k)):
            pass
        if pushed == len(ts):
            break
    assert feed_b.flush() and len(feed_b) == 0
    np.testing.assert_array_equal(ref_a.snapshot().heights_mm,
                                  ref_b.snapshot().heights_mm)
    feed_b.push(ts[5], poses[5])  # long integrated: dropped, the reference unchanged
    assert feed_b.flush() and len(feed_b) == 0
    np.testing.assert_array_equal(ref_a.snapshot().heights_mm,
                                  ref_b.snapshot().heights_mm)
    assert ref_a.snapshot().heights_mm.max() > 0.05
    assert ref_a.deposited_mm3 == pytest.approx(ref_b.deposited_mm3, rel=1e-12)


@pytest.mark.parametrize("factor", [1.3, 0.8])
def test_plume_calibration_on_the_deposit_box_equals_the_whole_plate_filter(factor):
    """set_plume_factor filters only the deposit's box (plus the kernel's reach); the heights
    are bit-identical to filtering the whole plate, also for a deposit at the plate's edge."""
    from scipy.ndimage import gaussian_filter, laplace

    proc = ProcessConfig()
    ref = NearNetReference(proc, MonitorConfig(), CAL, cell_mm=0.25, angle_from_surface=False)
    ts, T = straight_pass(proc)
    ref.add_states(ts, T)
    ny, nx = ref.heights_mm.shape
    ref.heights_mm[:40, nx // 2:nx // 2 + 30] += 0.5  # a deposit touching the plate's edge
    h, sigma = ref.heights_mm.copy(), ref.sigma_mm
    if factor > 1.0:
        want = gaussian_filter(h, sigma * math.sqrt(factor ** 2 - 1.0) / ref.cell_mm,
                               mode="nearest")
    else:
        want = np.maximum(h + (factor - 1.0) * sigma ** 2
                          * laplace(h, mode="nearest") / ref.cell_mm ** 2, 0.0)
    ref.set_plume_factor(factor)
    assert np.array_equal(ref.heights_mm, want)
    assert ref.sigma_mm == pytest.approx(sigma * factor)
    assert np.count_nonzero(h) < 0.2 * h.size  # the box is a small part of the plate
