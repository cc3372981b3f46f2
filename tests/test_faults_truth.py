"""Ground truth: per-layer surfaces and fault truth measured against a fault-free run."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh
from test_faults import _build_pad, _polygon_path

from twin.schema import FaultConfig
from twin.world.heightfield import HeightField
from twin.world.truth import fault_truth, write_fault_truth, write_layer_surface


def test_fault_truth_recovers_feed_drop_and_bump(tmp_path):
    faults = (FaultConfig(kind="feed_drop", layers=(3, 5), factor=0.5),
              FaultConfig(kind="bump", layers=(6, 6), center_O_mm=(17.0, 22.0), height_mm=1.2,
                          width_mm=3.0))
    nominal = _build_pad(())
    faulty = _build_pad(faults)
    truth = write_fault_truth(tmp_path / "faults.json", faults, faulty, nominal)
    assert json.loads((tmp_path / "faults.json").read_text()) == truth
    drop, bump = truth["faults"]
    x, y = nominal[-1].centres_mm()
    gain = nominal[-1].heights_mm[np.ix_((y > 16) & (y < 24), (x > 16) & (x < 24))].mean() / 8
    assert drop["sign"] == -1 and drop["layers"][0] == 3 and drop["layers"][-1] == 7
    assert drop["expected_deviation_mm"] == pytest.approx(-1.5 * gain, rel=0.15)
    bx0, by0, bx1, by1 = drop["region_O"]["bbox"]
    assert bx0 < 14 and by0 < 14 and bx1 > 26 and by1 > 26  # the pad's footprint
    assert bump["sign"] == 1 and bump["layers"][0] == 6
    # the bump sits on top of the drop's deficit; what it adds beyond it is its height
    assert bump["expected_deviation_mm"] - drop["expected_deviation_mm"] == pytest.approx(
        1.2, rel=0.15)
    bx0, by0, bx1, by1 = bump["region_O"]["bbox"]
    assert bx0 < 17 < bx1 and by0 < 22 < by1 and bx1 - bx0 < 7


def test_corner_dwell_truth_regions_sit_on_the_corners():
    tp, corners = _polygon_path([150.0, 90.0, 150.0])
    hf_nom = HeightField((80.0, 80.0), 0.5)
    hf_bad = hf_nom.copy()
    x, y = hf_bad.centres_mm()
    gx, gy = np.meshgrid(x, y)
    bumps = sum(0.5 * np.exp(-((gx - c[0]) ** 2 + (gy - c[1]) ** 2) / 8.0)
                for c in corners[[0, 2]])
    hf_bad.add_heights(bumps)
    truth = fault_truth((FaultConfig(kind="corner_dwell", corner_angle_deg=150.0,
                                     extra_dwell_s=0.3),), {1: hf_bad}, {1: hf_nom}, tp)
    f = truth["faults"][0]
    assert f["sign"] == 1 and f["layers"] == [1]
    assert f["expected_deviation_mm"] == pytest.approx(0.5, rel=0.05)
    got = np.array(f["region_O"]["centers"])
    assert len(got) == 2
    assert np.all(np.min(np.linalg.norm(got[:, None] - corners[None, [0, 2]], axis=2),
                         axis=1) < 1.0)
    with pytest.raises(ValueError, match="toolpath"):
        fault_truth((FaultConfig(kind="corner_dwell", corner_angle_deg=150.0,
                                 extra_dwell_s=0.3),), {1: hf_bad}, {1: hf_nom})


def test_layer_surface_ply_is_the_true_surface_in_O(tmp_path):
    hf = HeightField((60.0, 60.0), 0.5, 6.0)
    x, y = hf.centres_mm()
    gx, gy = np.meshgrid(x, y)
    hf.heights_mm = np.where((np.abs(gx - 30) < 5) & (np.abs(gy - 25) < 5), 2.0, 0.0)
    path = write_layer_surface(hf, tmp_path / "layer_003.ply")
    mesh = trimesh.load(path, process=False)
    lo, hi = mesh.bounds
    assert lo[0] == pytest.approx(15.25) and hi[0] == pytest.approx(44.75)
    assert lo[1] == pytest.approx(10.25) and hi[1] == pytest.approx(39.75)
    assert hi[2] == 2.0 and lo[2] == 0.0
    np.testing.assert_allclose(mesh.vertices[:, 2], hf.height_at(mesh.vertices[:, :2]))
    full = trimesh.load(write_layer_surface(hf, tmp_path / "full.ply", full=True), process=False)
    assert np.allclose(full.bounds[:, :2], [[0, 0], [60, 60]])
