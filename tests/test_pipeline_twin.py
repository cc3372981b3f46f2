"""Fusion of the twin's virtual profilers over a known static part (real cell geometry, nozzle
occlusion, 0.05 mm range noise): accuracy and coverage of the reconstruction at 0.5 mm voxels."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from dm2.core.config import MonitorConfig, parse_scenario
from dm2.core.frames import invert
from dm2.core.messages import RobotState
from dm2.fusion.fusion import TsdfFusion
from dm2.fusion.registration import register_profile

twin_cell = pytest.importorskip("twin.cell.cell")
from twin.profiler.occluders import nozzle_occluder  # noqa: E402
from twin.profiler.sensor import VirtualProfiler  # noqa: E402
from twin.world.heightfield import HeightField  # noqa: E402


def test_twin_profiles_of_a_static_part_reconstruct_within_a_quarter_millimetre():
    sc = parse_scenario({"name": "static_box", "seed": 3, "part": {"generator": "box"},
                         "noise": {"range_sigma_mm": 0.05}}, "test")
    cell = twin_cell.CellModel.from_scenario(sc)
    cal = cell.calibration()
    box = trimesh.creation.box(extents=(24.0, 18.0, 5.0))
    box.apply_translation((60.0, 60.0, 2.5))
    hf = HeightField.from_mesh(box, (120.0, 120.0), 0.25, 6.0)
    profilers = [VirtualProfiler(sid, cal.T_B_S[sid], sc.sensors, sc.noise, seed=7)
                 for sid in ("S1", "S2", "S3")]
    occ = [nozzle_occluder(cal.T_B_N, sc.cell)]
    # raster of the spot over the part top at 1 mm per frame set, lines 4 mm apart
    targets = []
    for i, y in enumerate(np.arange(50.0, 71.0, 4.0)):
        xs = np.arange(44.0, 77.0, 1.0)
        targets += [(x, y, 5.0) for x in (xs if i % 2 == 0 else xs[::-1])]
    targets = np.array(targets)
    T_B_O = cell.T_B_O_for(targets, np.tile([0.0, 0.0, -1.0], (len(targets), 1)))
    T_O_F = invert(cal.T_F_O)
    msgs, measured = [], []
    for k, T in enumerate(T_B_O):
        t = 1.0 + 0.1 * k
        for dt in (-0.02, 0.0, 0.02, 0.04, 0.06):  # robot states around the frame set
            msgs.append(RobotState(t + dt, 5 * k, np.zeros(6), T @ T_O_F))
        for j, prof in enumerate(profilers):
            p = prof.scan(hf, T, t + 0.02 * j, k, occ)
            msgs.append(p)
            T_O_S = invert(T) @ cal.T_B_S[prof.sensor_id]
            measured.append(register_profile(p.xz_S[p.valid], T_O_S)[0])
    msgs.sort(key=lambda m: m.stamp_s)  # the plate holds still during each frame set
    dedup = {}
    for m in msgs:
        dedup.setdefault((type(m).__name__, m.stamp_s), m)
    mon = TsdfFusion(cal, MonitorConfig(voxel_mm=0.5), sc.process)
    mon.feed_all(dedup.values())
    surf = mon.finish()[-1].surface
    truth = hf.to_mesh()
    sample = surf.vertices_O[np.random.default_rng(0).choice(surf.n_vertices, 4000,
                                                             replace=False)]
    _, dist, _ = trimesh.proximity.closest_point(truth, sample)
    rms = float(np.sqrt(np.mean(dist**2)))
    visible = np.concatenate(measured)[::9]
    near, _ = cKDTree(surf.vertices_O).query(visible)
    coverage = float(np.mean(near <= 1.0))
    print(f"twin static part: RMS {rms:.3f} mm to the true surface, coverage {100 * coverage:.1f}"
          f" % of the sensor-visible surface ({len(visible)} samples), drops {mon.dropped}")
    assert rms <= 0.25
    assert coverage >= 0.95
