"""The pre-fusion point filter (dm2.fusion.point_filter): known outliers on synthetic profiles
are found with their reason, and nothing else is, at edges, steps and gaps included."""

from __future__ import annotations

import numpy as np
import pytest

from dm2.core.config import PointFilterConfig
from dm2.fusion.point_filter import BURST, KEEP, SINGLE, PointFilter, line_outliers

CFG = PointFilterConfig()


def profile(seed: int, n: int = 640, sigma: float = 0.05):
    """A 50 mm line at about 100 mm range: a tilted flat, then a 1 mm step up at x = 10 mm, with
    Gaussian range noise ``sigma`` along z; (n, 2) [mm, S]."""
    rng = np.random.default_rng(seed)
    x = np.linspace(-25.0, 25.0, n)
    z = 100.0 + 0.2 * x + np.where(x > 10.0, -1.0, 0.0) + rng.normal(0.0, sigma, n)
    return np.column_stack([x, z])


def reasons(xz, offsets=None):
    offsets = np.array([0, xz.shape[0]]) if offsets is None else offsets
    out = np.empty(xz.shape[0], dtype=np.int8)
    line_outliers(np.ascontiguousarray(xz), offsets, CFG.reject_mm, CFG.agree_mm,
                  CFG.max_step_mm, CFG.max_run_points, out)
    return out


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_clean_profile_loses_nothing(seed):
    # a clean profile (range noise, a tilt, a 1 mm step edge) keeps every point
    assert np.all(reasons(profile(seed)) == KEEP)


def test_fragments_across_gaps_are_kept():
    # a profile in fragments (an occluded wall): short stretches far apart are surface
    xz = profile(5)
    keep = np.zeros(len(xz), bool)
    for a in (0, 60, 64, 70, 200, 203, 400):
        keep[a:a + 4] = True
    keep[410:] = True
    assert np.all(reasons(xz[keep]) == KEEP)


def test_ghost_particle_and_burst_found_with_their_reason():
    xz = profile(7)
    xz[300, 1] += 2.0  # a ghost 2 mm behind the surface
    xz[100, 1] -= 3.0  # a powder particle 3 mm in front of it
    xz[380:390, 1] += 1.0  # a burst: ten points misread by 1 mm together
    xz[200:203, 1] -= 0.6  # a short burst in front
    got = reasons(xz)
    want = np.zeros(len(xz), np.int8)
    want[[300, 100]] = SINGLE
    want[380:390] = BURST
    want[200:203] = BURST
    np.testing.assert_array_equal(got, want)


def test_run_longer_than_max_run_is_kept():
    # a stretch longer than max_run_points is a surface the filter cannot judge: kept
    xz = profile(8)
    xz[300:300 + CFG.max_run_points + 1, 1] += 1.0
    assert np.all(reasons(xz) == KEEP)


def test_filter_counts_by_sensor_and_reason_and_drops_the_points():
    a, b = profile(11), profile(12)
    a[50, 1] += 2.0
    b[500:504, 1] += 1.5
    b[600, 1] -= 1.0
    xz = np.concatenate([a, b, profile(13)])
    offsets = np.array([0, 640, 1280, 1920])
    pf = PointFilter(CFG.reject_mm, CFG.agree_mm, CFG.max_step_mm, CFG.max_run_points,
                     ["S1", "S2", "S3"])
    out, out_offsets = pf.apply(xz, offsets, [1, 2, 1])  # profiles of S2, S3, S2
    np.testing.assert_array_equal(out_offsets, [0, 639, 1274, 1914])
    assert not np.isin(xz[[50, 640 + 500, 640 + 600], 1], out[:, 1]).any()
    assert pf.counts() == {"point_filter_single": 2, "point_filter_burst": 4}
    s = pf.summary()
    assert s["points"] == 1920 and s["rejected"] == 6
    assert s["by_sensor"]["S2"] == {"points": 1280, "rejected": 1, "share": 1 / 1280,
                                    "single": 1, "burst": 0}
    assert s["by_sensor"]["S3"]["burst"] == 4 and s["by_sensor"]["S3"]["single"] == 1
    assert s["by_sensor"]["S1"]["points"] == 0


def test_clean_batch_is_passed_through_unchanged():
    xz = profile(21)
    offsets = np.array([0, 640])
    pf = PointFilter(CFG.reject_mm, CFG.agree_mm, CFG.max_step_mm, CFG.max_run_points, ["S1"])
    out, out_offsets = pf.apply(xz, offsets, [0])
    assert out is xz and out_offsets is offsets and pf.counts() == {}


def test_a_sensor_rejecting_far_more_than_usual_is_a_finding_in_the_verdict():
    from dm2.report.summary import verdict

    report = {"layers": [], "tracks": [], "point_filter": {"by_sensor": {
        "S1": {"points": 1000, "rejected": 4, "share": 0.004},
        "S2": {"points": 1000, "rejected": 140, "share": 0.14},
        "S3": {"points": 1000, "rejected": 19, "share": 0.019}}}}
    v = verdict(report)
    assert v["sentences"] == ["Sensor finding: S2 rejected 14 % of its points as not surface "
                              "(window dirty, or spatter on the line?)."]
    assert v["findings"] == 1 and v["defects"] == 0
    assert verdict({"layers": [], "tracks": []})["findings"] == 0


def test_the_finding_says_since_which_layer_and_the_layers_are_counted():
    from dm2.report.summary import sensor_findings

    pf = PointFilter(CFG.reject_mm, CFG.agree_mm, CFG.max_step_mm, CFG.max_run_points,
                     ["S1", "S2"])
    for layer in range(4):  # S2's window gets dirty at layer 2: a ghost in each profile
        for _ in range(10):
            a, b = profile(layer), profile(layer + 10)
            if layer >= 2:
                b[100, 1] += 2.0
                b[300:305, 1] += 1.5
            pf.apply(np.concatenate([a, b]), np.array([0, 640, 1280]), [0, 1])
        pf.close_layer(layer)
    s = pf.summary()
    assert [lay["rejected"] for lay in s["by_layer"]] == [
        {"S1": 0, "S2": 0}, {"S1": 0, "S2": 0}, {"S1": 0, "S2": 60}, {"S1": 0, "S2": 60}]
    assert all(lay["points"] == {"S1": 6400, "S2": 6400} for lay in s["by_layer"])
    # over the whole run S2 lost 120 / 25600 = 0.5 %: under the finding's 2 %
    assert sensor_findings({"point_filter": s}) == []
    # the same rate in a sensor with fewer points: 6 of 100 per layer from layer 2 on
    report = {"point_filter": {"by_sensor": {"S2": {"share": 0.03}}, "by_layer": [
        {"layer": k, "points": {"S2": 100}, "rejected": {"S2": 0 if k < 2 else 6}}
        for k in range(4)]}}
    assert sensor_findings(report) == ["S2 rejected 6 % of its points since layer 2 as not "
                                       "surface (window dirty, or spatter on the line?)"]
