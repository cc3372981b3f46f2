"""Real-time deviation: exact column deviation, and a defect flagged within 1 s of its start."""

import numpy as np
import pytest

from dm2.core.config import MonitorConfig
from dm2.defects.realtime import OVER, UNDER, RealtimeDeviation
from dm2.fusion.tsdf.field import SparseTSDF
from dm2.reference.height_map import ReferenceMap

MON = MonitorConfig()
CELL = 0.25


def pad(height=2.4, side=60.0, size=120.0):
    n = int(size / CELL)
    c = (np.arange(n) + 0.5) * CELL
    xx, yy = np.meshgrid(c, c)
    inside = (np.abs(xx - 60) <= side / 2) & (np.abs(yy - 60) <= side / 2)
    return np.where(inside, height, 0.0)


def bump(xy, centre=(60.0, 60.0), height=1.0, fwhm=5.0):
    s = fwhm / 2.3548
    r2 = ((xy[:, 0] - centre[0]) ** 2 + (xy[:, 1] - centre[1]) ** 2)
    return height * np.exp(-r2 / (2 * s * s))


def test_dense_box_gives_exact_signed_deviation():
    ref = ReferenceMap(pad(), CELL)
    rt = RealtimeDeviation(MON)
    v = MON.voxel_mm
    origin = (100, 100, 0)  # x, y from 50 mm, z from 0
    nx, ny, nz = 20, 20, 16
    zc = (np.arange(nz) + 0.5) * v
    surface = np.full((nx, ny), 2.4 + 0.7)
    surface[:, 10:] = 2.4 - 0.55  # half the box under, half over
    surface[:5, :] = 2.4 + 0.1  # a strip inside the tolerance
    d = (zc[None, None, :] - surface[:, :, None]).astype(np.float32)
    w = np.full(d.shape, 3.0, np.float32)
    w[15:, :, :] = 0.0  # unobserved columns: no deviation at all
    fd = rt.update(1.0, d, w, origin, ref)
    assert len(fd.deviation_mm) == 15 * 20
    gi = np.round(fd.xy_O[:, 0] / v - 0.5).astype(int) - 100
    gj = np.round(fd.xy_O[:, 1] / v - 0.5).astype(int) - 100
    assert np.allclose(fd.deviation_mm, surface[gi, gj] - 2.4, atol=1e-5)
    assert fd.over_area_mm2 == pytest.approx(10 * 10 * v * v)
    assert fd.under_area_mm2 == pytest.approx(10 * 10 * v * v)
    assert rt.flagged_area_mm2(OVER) == pytest.approx(25.0)
    assert fd.alarms == ()  # one comparison is no evidence: the flags must persist
    stamps = np.linspace(1.0 + MON.realtime_persist_s / 2, 1.01 + MON.realtime_persist_s,
                         MON.realtime_min_observations)
    for k, t in enumerate(stamps):  # observed again: the weights grow, the surface stays
        fd = rt.update(float(t), d, w * (k + 2), origin, ref)
        if k < len(stamps) - 1:
            assert fd.alarms == ()
    assert {a.kind for a in fd.alarms} == {"overbuild", "underbuild"}
    assert all(a.first_flag_s == 1.0 for a in fd.alarms)
    assert np.isnan(rt.deviation_map_mm[100 + 5, 100 + 16])  # (row y, column x) unobserved


def _sensor_lines(spot, n=400, half_len=20.0):
    """Three laser lines through the spot and their sensor origins (95 mm, 55 deg up)."""
    pts, origins = [], []
    for az in np.radians([90.0, 210.0, 330.0]):
        u = np.array([np.cos(az), np.sin(az)])
        across = np.array([-u[1], u[0]])
        s = np.linspace(-half_len, half_len, n)
        xy = spot[:2] + s[:, None] * across
        o = np.array([*(spot[:2] + 95 * np.cos(np.radians(55)) * u),
                      spot[2] + 95 * np.sin(np.radians(55))])
        keep = np.all(np.abs(xy - 60.0) < 28.0, axis=1)  # the pad's top, away from its walls
        pts.append(xy[keep])
        origins.append(np.tile(o, (int(keep.sum()), 1)))
    return np.vstack(pts), np.vstack(origins)


def _run(defect: bool):
    ref = ReferenceMap(pad(), CELL)
    tsdf = SparseTSDF(MON.voxel_mm, MON.truncation_voxels * MON.voxel_mm, MON.weight_cap)
    rt = RealtimeDeviation(MON)
    v_mm_s, t0 = 30.0, 25.0 / 30.0  # the spot reaches x = 60 at t0
    for k in range(int(2.0 * 10)):
        t = k / 10.0
        spot = np.array([35.0 + v_mm_s * t, 60.0, 2.4])
        xy, origins = _sensor_lines(spot)
        z = ref.height_at(xy) + (bump(xy) if defect and t >= t0 else 0.0)
        pts = np.column_stack([xy, z])
        tsdf.integrate(origins, pts, np.ones(len(pts), bool))
        rt.update_from_tsdf(tsdf, spot, t, ref)
    return rt, t0


def test_defect_flagged_within_one_second_of_process_time():
    rt, t0 = _run(defect=True)
    over = [a for a in rt.alarms if a.kind == "overbuild"]
    assert over and not [a for a in rt.alarms if a.kind == "underbuild"]
    first = over[0]
    assert t0 <= first.stamp_s <= t0 + 1.0
    assert np.allclose(first.centroid_xy_O, (60.0, 60.0), atol=2.0)
    assert first.area_mm2 >= MON.min_region_area_mm2
    assert np.nanmax(rt.deviation_map_mm) == pytest.approx(1.0, abs=0.15)
    assert rt.flagged_area_mm2(UNDER) == 0.0


def test_fault_free_stream_raises_no_alarm():
    rt, _ = _run(defect=False)
    assert rt.alarms == []
    assert np.nanmax(np.abs(rt.deviation_map_mm)) < 0.25  # sparse oblique rays: ~0.2 mm
    assert not rt.flag_map.any()


def test_sloped_reference_deviation_is_projected_on_its_normal_like_numpy():
    """The compiled comparison equals the formula in numpy: bilinear reference heights at the
    voxel columns, slopes by np.gradient, deviation (z - h) / sqrt(1 + |grad h|^2)."""
    from dm2.reference.height_map import bilinear_height

    rng = np.random.default_rng(7)
    c = (np.arange(480) + 0.5) * CELL
    xx, yy = np.meshgrid(c, c)
    heights = 2.0 + 0.8 * np.sin(xx / 7.0) * np.cos(yy / 5.0)
    ref = ReferenceMap(heights, CELL)
    rt = RealtimeDeviation(MON)
    v = MON.voxel_mm
    origin = (90, 70, 0)
    nx, ny, nz = 24, 20, 12
    zc = (np.arange(nz) + 0.5) * v
    surface = rng.uniform(1.2, 4.5, (nx, ny))
    d = (zc[None, None, :] - surface[:, :, None]).astype(np.float32)
    w = np.full(d.shape, 3.0, np.float32)
    w[:3] = 0.0  # three unobserved column rows
    fd = rt.update(2.0, d, w, origin, ref)

    gx_c = (np.arange(origin[0], origin[0] + nx) + 0.5) * v
    gy_c = (np.arange(origin[1], origin[1] + ny) + 0.5) * v
    X, Y = np.meshgrid(gx_c, gy_c)
    hw = bilinear_height(heights, CELL, np.column_stack([X.ravel(), Y.ravel()])).reshape(ny, nx)
    gy, gx = np.gradient(hw, v)
    ii = np.round(fd.xy_O[:, 0] / v - 0.5).astype(int) - origin[0]
    jj = np.round(fd.xy_O[:, 1] / v - 0.5).astype(int) - origin[1]
    assert len(fd.deviation_mm) == (nx - 3) * ny and ii.min() == 3
    k = np.floor(surface[ii, jj] / v - 0.5)  # the crossing interpolates linearly: exact z
    z = (k + (surface[ii, jj] - (k + 0.5) * v) / v + 0.5) * v
    want = (z - hw[jj, ii]) / np.sqrt(1.0 + gx[jj, ii] ** 2 + gy[jj, ii] ** 2)
    assert np.allclose(fd.deviation_mm, want, atol=1e-5)
    assert np.abs(want).max() > 1.0 and np.any(np.hypot(gx, gy) > 0.1)  # sloped, flagged
    dg = MON.delta_global_mm
    assert np.array_equal(fd.flag, np.where(want > dg, OVER, np.where(want < -dg, UNDER, 0)))
    assert np.allclose(rt.deviation_map_mm[jj + origin[1], ii + origin[0]], want, atol=1e-5)
    assert np.all(rt.first_flag_s[jj + origin[1], ii + origin[0]][fd.flag != 0] == 2.0)


def _patch_alarms_scipy(flags, kind, deviation_mm, alarmed, first_flag_s, link, min_cells):
    """The alarm patches with scipy.ndimage: the definition the compiled search follows."""
    from scipy import ndimage

    hit = flags == kind
    unseen = np.isnan(deviation_mm)
    patch = (ndimage.binary_closing(hit, link) & (hit | unseen)) | hit
    labels, n = ndimage.label(patch, structure=np.ones((3, 3), bool))
    sizes = np.bincount(labels.ravel(), minlength=n + 1)
    already = np.bincount(labels[alarmed].ravel(), minlength=n + 1)
    flagged = np.bincount(labels[hit].ravel(), minlength=n + 1)
    out = []
    for lab in np.flatnonzero((sizes >= min_cells) & (already == 0) & (flagged > 0)):
        if lab:
            rows, cols = np.nonzero(labels == lab)
            out.append((sizes[lab], rows.mean(), cols.mean(),
                        np.nanmin(first_flag_s[rows, cols][hit[rows, cols]])))
            alarmed[rows, cols] = True
    return out


def test_alarm_patches_equal_scipy_closing_and_labelling():
    from dm2.defects.realtime_kernels import patch_alarms

    rng = np.random.default_rng(12)
    yy, xx = np.mgrid[-4:5, -4:5]
    link = xx * xx + yy * yy <= 16
    n_alarms = 0
    for k in range(40):
        h, w = rng.integers(20, 90, 2)
        flags = rng.choice([0, 1, 2], size=(h, w), p=[0.8, 0.12, 0.08]).astype(np.int8)
        if k % 2:
            flags[rng.random((h, w)) < 0.5] = 0  # sparse lines of flagged columns
        else:  # runs of flagged columns along the rows, as on a flagged top
            flags = np.repeat(flags[:, ::4], 4, axis=1)[:, :w]
        dev = np.where(rng.random((h, w)) < 0.6, np.nan, 0.1)  # mostly unobserved between
        dev[flags != 0] = 0.5
        first = np.where(flags != 0, rng.uniform(0, 10, (h, w)), np.nan)
        alarmed = rng.random((h, w)) < 0.01
        want_alarmed, got_alarmed = alarmed.copy(), alarmed.copy()
        for kind in (OVER, UNDER):
            want = _patch_alarms_scipy(flags, kind, dev, want_alarmed, first, link, 6.0)
            sizes, stats = patch_alarms(flags, kind, dev, got_alarmed, first, link, 6.0)
            got = [(s, *row) for s, row in zip(sizes, stats, strict=True)]
            assert np.isfinite(np.asarray(stats)[:, 2]).all()  # every alarm holds a flag
            np.testing.assert_equal(np.array(got, float).reshape(-1, 4),
                                    np.array(want, float).reshape(-1, 4))
            n_alarms += len(got)
        assert np.array_equal(got_alarmed, want_alarmed)
    assert n_alarms > 50


def test_island_of_unobserved_columns_raises_no_alarm():
    """Unobserved columns bridged by the closing but walled off from the flagged ones by
    observed-normal columns form a patch of their own: it shows no defect, so no alarm."""
    from dm2.defects.realtime_kernels import patch_alarms

    h, w = 30, 30
    flags = np.zeros((h, w), np.int8)
    dev = np.full((h, w), 0.05)  # observed, normal
    first = np.full((h, w), np.nan)
    flags[5:25, 5] = flags[5:25, 11] = OVER  # two flagged lines of 20 columns, 6 apart
    dev[flags == OVER] = 0.8
    first[flags == OVER] = 3.0
    dev[5:25, 8] = np.nan  # unobserved line midway, walled off by normal columns 6-7, 9-10
    yy, xx = np.mgrid[-4:5, -4:5]
    link = xx * xx + yy * yy <= 16
    alarmed = np.zeros((h, w), bool)
    sizes, stats = patch_alarms(flags, OVER, dev, alarmed, first, link, 6.0)
    assert sorted(sizes.tolist()) == [20, 20]  # the two flagged lines, not the island
    assert np.all(stats[:, 2] == 3.0)
    assert not alarmed[:, 8].any() and alarmed[5:25, 5].all() and alarmed[5:25, 11].all()


def test_reference_growing_over_an_earlier_measurement_is_no_evidence():
    """A column is judged on new measurement only, held against the interval from the
    reference at its previous observation to the reference now: deposition that the
    profilers have not seen yet raises nothing, a surface that stays low once the
    deposition there is over is underbuilt."""
    v = MON.voxel_mm
    origin = (100, 100, 0)
    nx, ny, nz = 20, 20, 16
    zc = (np.arange(nz) + 0.5) * v
    d = np.broadcast_to(zc[None, None, :] - 2.4, (nx, ny, nz)).astype(np.float32)
    w = np.full(d.shape, 3.0, np.float32)
    rt = RealtimeDeviation(MON)
    fd = rt.update(1.0, d, w, origin, ReferenceMap(pad(2.4), CELL))
    assert not fd.flag.any()
    grown = ReferenceMap(pad(3.2), CELL)  # 0.8 mm deposited since, not yet observed
    for t in np.arange(1.1, 3.0, 0.1):  # the same TSDF compared again and again
        fd = rt.update(float(t), d, w, origin, grown)
        assert fd.alarms == () and not fd.flag.any()
    # observed anew: the surface may still lag the deposition it saw start ...
    fd = rt.update(3.0, d, w + 1, origin, grown)
    assert not fd.flag.any() and np.allclose(fd.deviation_mm, 0.0)
    # ... but observed again at 2.4 mm, once the reference has stood at 3.2 mm: underbuild
    alarms = []
    for k, t in enumerate((3.1, 3.2, 3.3)):
        fd = rt.update(t, d, w + 2 + k, origin, grown)
        assert (fd.flag == UNDER).all()
        assert np.allclose(fd.deviation_mm, -0.8, atol=1e-5)
        alarms += fd.alarms
    assert [a.kind for a in alarms] == ["underbuild"] and alarms[0].first_flag_s == 3.1


def test_the_live_reference_brings_its_plume_term_like_a_layer_map():
    """The session compares against the live NearNetReference, the layer analysis against its
    ReferenceMap snapshots: both carry the plume width, so the plume term (sigma^2 times the
    reference's laplacian) widens the bound where the reference curves in both."""
    from test_reference import CAL

    from dm2.core.config import ProcessConfig
    from dm2.reference.model import NearNetReference

    live = NearNetReference(ProcessConfig(), MON, CAL, cell_mm=CELL)
    sigma = live.sigma_mm
    c = (np.arange(live.heights_mm.shape[1]) + 0.5) * CELL
    xx, _ = np.meshgrid(c, c)
    s_mm = 6.0  # a broad ridge along y, 3 mm high: curved (laplacian -h/s^2 at the crest), yet
    live.heights_mm[:] = 3.0 * np.exp(-(xx - 60.0) ** 2 / (2 * s_mm ** 2))  # not an edge
    assert live.plume_sigma_mm == sigma == live.snapshot().plume_sigma_mm
    v = MON.voxel_mm
    origin = (100, 110, 0)  # x 50..70 mm: across the ridge
    nx, ny, nz = 40, 20, 16
    gx = (np.arange(origin[0], origin[0] + nx) + 0.5) * v
    crest = 3.0 * np.exp(-(gx - 60.0) ** 2 / (2 * s_mm ** 2))
    surface = np.repeat((crest + MON.delta_global_mm + 0.03)[:, None], ny, axis=1)
    d = ((np.arange(nz) + 0.5)[None, None, :] * v - surface[:, :, None]).astype(np.float32)
    w = np.full(d.shape, 6.0, np.float32)
    strong = {}
    for name, ref in (("live", live),
                      ("layer map", ReferenceMap(live.heights_mm, CELL, plume_sigma_mm=sigma)),
                      ("no plume width", ReferenceMap(live.heights_mm, CELL))):
        rt = RealtimeDeviation(MON)
        fd = rt.update(1.0, d, w, origin, ref)
        gi = np.round(fd.xy_O[:, 0] / v - 0.5).astype(int)
        gj = np.round(fd.xy_O[:, 1] / v - 0.5).astype(int)
        strong[name] = rt.strong_map[gj, gi]  # past delta_global and the confidence bound
    np.testing.assert_array_equal(strong["live"], strong["layer map"])
    # at the crest (x 60 mm) the surface stands 0.03 mm past delta_global: strong evidence
    # without the plume term (bound 3 x 0.135 mm); with it the bound also holds
    # plume_rel sigma^2 |laplacian| (3 x 0.153 mm)
    crest_cols = np.abs(fd.xy_O[:, 0] - 60.0) < 0.5
    assert crest_cols.sum() == 2 * ny
    assert np.all(strong["no plume width"][crest_cols])
    assert not np.any(strong["live"][crest_cols])
