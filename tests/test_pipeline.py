"""End-to-end fusion on analytic scenes: accuracy, coverage, dynamic following, layers."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree
from test_monitor_scene import Scene, make_calibration, raster_lines, raster_run

import dm2.fusion.fusion as pipeline_mod
from dm2.core.config import MonitorConfig, ProcessConfig
from dm2.core.messages import LayerMark, Toolpath
from dm2.fusion.fusion import TsdfFusion
from dm2.fusion.registration import register_profiles


@pytest.fixture(scope="module")
def cal():
    return make_calibration()


def test_registration_puts_every_point_on_the_true_surface(cal, monkeypatch):
    scene = Scene(boxes=[((50, 50, 0), (66, 66, 6))])
    msgs, hits = raster_run(scene, cal, [((40, 58, 0), (80, 58, 0))], step_mm=4.0)
    got = []
    real = pipeline_mod.SparseTSDF.integrate_profiles

    def spy(self, xz_S, offsets, T_O_S, *args):
        got.append(register_profiles(xz_S, offsets, T_O_S)[0])
        return real(self, xz_S, offsets, T_O_S, *args)

    monkeypatch.setattr(pipeline_mod.SparseTSDF, "integrate_profiles", spy)
    mon = TsdfFusion(cal, MonitorConfig(), ProcessConfig())
    mon.feed_all(msgs)
    mon.finish()
    pts = np.concatenate(got)
    assert len(pts) == len(hits) == mon.points_fused
    np.testing.assert_allclose(pts, hits, atol=1e-9)
    assert mon.dropped == {}


def test_static_part_is_reconstructed_within_a_quarter_millimetre(cal):
    scene = Scene(boxes=[((50, 50, 0), (66, 66, 6))], spheres=[((78, 46, -4), 10.0)])
    msgs, hits = raster_run(scene, cal, raster_lines((38, 92), np.arange(38, 74, 6.0)),
                            step_mm=1.5, noise_mm=0.05, seed=3)
    mon = TsdfFusion(cal, MonitorConfig(voxel_mm=0.5), ProcessConfig())
    mon.feed_all(msgs)
    surf = mon.finish()[-1].surface
    dist = scene.sdf(surf.vertices_O)
    rms = float(np.sqrt(np.mean(dist**2)))
    near, _ = cKDTree(surf.vertices_O).query(hits[::5])
    coverage = float(np.mean(near <= 1.0))
    print(f"static reconstruction: RMS {rms:.3f} mm, coverage {100 * coverage:.1f} % "
          f"of the sensor-visible surface, {surf.n_vertices} vertices")
    assert rms <= 0.25
    assert coverage >= 0.95
    # outward normals on the box top and plate
    top = surf.vertices_O[:, 2] > 5.8
    assert np.mean(surf.normals_O[top, 2]) > 0.95


def _region_mean_z(surf, y_lo, y_hi):
    v = surf.vertices_O
    m = (v[:, 0] > 45) & (v[:, 0] < 75) & (v[:, 1] > y_lo) & (v[:, 1] < y_hi)
    assert m.sum() > 100
    return float(v[m, 2].mean())


def test_raised_active_surface_is_followed_and_inactive_surface_stays(cal):
    flat = Scene()
    raised = Scene(boxes=[((30, 57.5, -1), (90, 62.5, 1.0))])  # +1 mm strip under the spot
    mon = TsdfFusion(cal, MonitorConfig(), ProcessConfig())
    assert mon.active_radius_mm > 2.5  # the strip lies inside the active region
    state = {"t": 0.0, "c": 0}

    def one_pass(scene, k):
        a, b = (25, 60, 0), (95, 60, 0)
        msgs, _ = raster_run(scene, cal, [(a, b) if k % 2 == 0 else (b, a)], step_mm=1.0,
                             noise_mm=0.05, seed=k, t0_s=state["t"], counter0=state["c"])
        state["t"], state["c"] = msgs[-1].stamp_s + 0.2, state["c"] + 1000
        mon.feed_all(msgs)
        return mon.surface()

    for k in range(3):
        surf = one_pass(flat, k)
    inactive0 = _region_mean_z(surf, 70, 76)
    assert abs(_region_mean_z(surf, 58.5, 61.5)) < 0.05
    heights = []
    for k in range(3, 8):
        surf = one_pass(raised, k)
        heights.append(_region_mean_z(surf, 58.5, 61.5))
        moved = abs(_region_mean_z(surf, 70, 76) - inactive0)
        assert moved < 0.05, f"inactive surface moved {moved:.3f} mm"
    print("strip height per pass after a 1 mm rise:", np.round(heights, 3))
    assert abs(heights[-1] - 1.0) <= 0.1
    assert heights[0] > 0.5  # already most of the way after one pass


def _track_z(surf):
    """Median height under the spot's track (the active region of these runs)."""
    v = surf.vertices_O
    m = (v[:, 0] > 44) & (v[:, 0] < 56) & (np.abs(v[:, 1] - 60) < 2)
    return float(np.median(v[m, 2]))


def _two_layers(cal):
    """Layer 0 on the bare plate, layer 1 on a 0.8 mm layer; the spot goes 40 -> 62 -> 40
    along y = 60 in each."""
    out, t0 = [], 0.0
    for k, scene in enumerate((Scene(), Scene(boxes=[((30, 30, -1), (90, 90, 0.8))]))):
        z = 0.8 * k
        lines = [((40, 60, z), (62, 60, z)), ((62, 60, z), (40, 60, z))]
        msgs, _ = raster_run(scene, cal, lines, step_mm=1.0, t0_s=t0, counter0=1000 * k)
        t0 = msgs[-1].stamp_s + 0.1
        out.append(msgs)
    return out


def test_layers_follow_layer_marks(cal):
    msgs0, msgs1 = _two_layers(cal)
    stream = [LayerMark(0.0, 0)] + msgs0 + [LayerMark(msgs0[-1].stamp_s + 0.05, 1)] + msgs1
    done = []
    mon = TsdfFusion(cal, MonitorConfig(), ProcessConfig(), on_layer_done=done.append)
    mon.feed_all(stream)
    mon.finish()
    assert [ls.layer for ls in mon.layer_done] == [0, 1] and done == mon.layer_done
    z0, z1 = _track_z(mon.surface(0)), _track_z(mon.surface(1))
    assert abs(z0) < 0.05 and abs(z1 - 0.8) < 0.1
    with pytest.raises(KeyError):
        mon.surface(7)


def test_older_layer_meshes_wait_on_disk_and_read_back_the_same(cal):
    from dm2.io.spill import Spilled

    msgs0, msgs1 = _two_layers(cal)
    stream = [LayerMark(0.0, 0)] + msgs0 + [LayerMark(msgs0[-1].stamp_s + 0.05, 1)] + msgs1
    runs = {}
    for keep in (None, 1):
        mon = TsdfFusion(cal, MonitorConfig(layers_in_memory=keep), ProcessConfig())
        mon.feed_all(stream)
        mon.finish()
        runs[keep] = mon
    assert isinstance(runs[1].layer_done[0]._surface, Spilled)  # layer 0 is on disk
    assert not isinstance(runs[None].layer_done[0]._surface, Spilled)
    for layer in (0, 1):
        a, b = runs[None].surface(layer), runs[1].surface(layer)
        for name in ("vertices_O", "faces", "weight", "normals_O"):
            assert np.array_equal(getattr(a, name), getattr(b, name)), (layer, name)
    assert abs(_track_z(runs[1].surface(0))) < 0.05  # the bare plate layer, read back


def test_layers_follow_the_toolpath_without_marks(cal):
    n = 12
    pos = np.array([[40 + 2 * i, 60, 0.0] for i in range(n)] +
                   [[62 - 2 * i, 60, 0.0] for i in range(n)] +
                   [[40 + 2 * i, 60, 0.8] for i in range(n)] +
                   [[62 - 2 * i, 60, 0.8] for i in range(n)])
    n *= 2
    lay = np.repeat([0, 1], n)
    tp = Toolpath(pos, np.tile([0, 0, -1.0], (2 * n, 1)), np.full(2 * n, 30.0),
                  np.zeros(2 * n), lay, np.ones(2 * n, bool), np.zeros(2 * n))
    msgs0, msgs1 = _two_layers(cal)
    mon = TsdfFusion(cal, MonitorConfig(), ProcessConfig(), toolpath=tp)
    mon.feed_all(msgs0 + msgs1)
    assert mon.current_layer == 1
    mon.finish()
    assert [ls.layer for ls in mon.layer_done] == [0, 1]
    assert abs(_track_z(mon.surface(0))) < 0.05 and abs(_track_z(mon.surface(1)) - 0.8) < 0.1


def test_without_marks_or_toolpath_the_run_is_one_layer(cal):
    msgs, _ = raster_run(Scene(), cal, [((40, 60, 0), (60, 60, 0))], step_mm=2.0)
    mon = TsdfFusion(cal, MonitorConfig(), ProcessConfig())
    mon.feed_all(msgs)
    assert mon.layer_done == []
    assert [ls.layer for ls in mon.finish()] == [0]
    assert mon.finish() is mon.layer_done  # idempotent


def test_points_outside_the_monitored_bounds_are_counted_out_of_range(cal):
    msgs, hits = raster_run(Scene(), cal, [((40, 60, 0), (60, 60, 0))], step_mm=2.0)
    bounds = ((50.0, 0.0, -10.0), (120.0, 120.0, 50.0))
    mon = TsdfFusion(cal, MonitorConfig(voxel_mm=2.0), ProcessConfig(), bounds_O=bounds)
    mon.feed_all(msgs)
    surf = mon.finish()[-1].surface
    outside = int(np.count_nonzero(hits[:, 0] < 50.0))
    assert outside > 1000
    assert mon.dropped == {"out_of_range": outside}
    assert mon.points_fused == len(hits) - outside
    assert surf.vertices_O[:, 0].min() > 50.0 - 2 * 2.0  # 2 mm voxels
    assert abs(np.median(surf.vertices_O[:, 2])) < 0.1
