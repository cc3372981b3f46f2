"""Fusion benchmark: points fused per second (sync + registration + TSDF), per-frame-set latency,
surface extraction per layer, peak memory, on synthetic profiles over a twisted-tower-sized
volume (60 x 60 x 100 mm).

The batched replay (``batch_profiles=REPLAY_BATCH_PROFILES``) is compared in the same process
with one kernel call per frame set (``batch_profiles=3``, the default for live and sessions), and
the two-thread TSDF update (``SparseTSDF(threads=2)``, bit-identical) with the one-thread kernel.
The load average is printed first: on a shared machine the second thread only helps when a
second core is idle. With the package defaults (``deposit_weight_cap`` set) the weights around
each profile's spray axis are capped before its points are fused (dm2.fusion.tsdf.deposit); with
two threads each caps its own block columns in profile order, so the field is still the serial
kernel's bit for bit. The kernel-alone line has no cap. The CPU-time line is load-independent:
the replay's CPU seconds outside the two threads plus, for each batch, the slower thread's
seconds, i.e. the replay's critical path on two idle cores.

Three profilers (640 points each) look at a growing 60 x 60 mm block while the spot rasters over
its top, which rises 100 mm over the run. Profiles are cast analytically before timing starts.

The peer: the same stream integrated by Open3D's ``VoxelBlockGrid`` (:mod:`open3d_peer`: one depth
image per profile with the sensor's fan as intrinsics, the same 0.5 mm voxel, +-3-voxel truncation,
8**3 blocks and 2 threads), printed as points/s and the ratio; surface extraction of both from the
same stream (median of ``--repeats``, at least 7); and the accuracy of both against the analytic
truth on a static scene (a box with a sphere cap on the plate, rastered by the same sensors), where
the truth is the scene itself. Ours meshes that scene twice: with the package defaults, which
assume the spray deposits under every profile (the weights around the spray axis capped,
dm2.fusion.tsdf.deposit, and the active window), and as a scan with the spray off (no deposit cap,
weights averaged up to 1e4 like Open3D's running mean). The end-to-end rate and the static scene
are also printed with ``[monitor] ray_merge_voxels = 0.5`` (off by default: neighbouring profile
points fused as one ray weighted by their number, dm2.fusion.profile_merge). Like for like with
Open3D, the scan (spray off) is also timed on the stream, interleaved with Open3D, without and
with merged rays: its accuracy is the static scene's scan figures. On a static scene the
defaults' deposit cap only costs accuracy; the part the monitor watches grows, so all of them and
Open3D are also timed and measured on a growing part (:mod:`growing_part`: a block whose top rises
0.8 mm a pass, against the final block).

Run: ``.venv/bin/python benchmarks/fusion.py [--frames 1200] [--repeats 3]``
"""

from __future__ import annotations

import argparse
import os
import resource
import statistics
import sys
import time
import tracemalloc
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import open3d_peer  # noqa: E402, I001  (sets Open3D's thread count before Open3D is imported)
import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
import growing_part  # noqa: E402  (imports test_monitor_scene)
from test_monitor_scene import Scene, make_calibration, raster_lines, raster_run  # noqa: E402

from dm2.core.config import MonitorConfig, ProcessConfig  # noqa: E402
from dm2.core.messages import Profile  # noqa: E402
from dm2.fusion.fusion import REPLAY_BATCH_PROFILES, TsdfFusion  # noqa: E402
from dm2.fusion.surface import SurfaceExtractor  # noqa: E402
from dm2.fusion.tsdf.field import MIN_SPLIT_POINTS, SparseTSDF  # noqa: E402

OPENMP_IDLE_S = 1.0  # after Open3D's last call, before ours is timed alone
EXTRACTION_REPEATS = 7  # at least this many timings of each extraction from scratch
MERGED = MonitorConfig(ray_merge_voxels=0.5)  # neighbouring points as one ray (profile_merge)
# Open3D's semantics: a scan with the spray off (no deposit cap, weights averaged up to 1e4 like
# its running mean), without and with neighbouring points merged
SCAN = MonitorConfig(deposit_weight_cap=None, weight_cap=1e4)
SCAN_MERGED = MonitorConfig(deposit_weight_cap=None, weight_cap=1e4, ray_merge_voxels=0.5)


def make_stream(frames: int):
    """Messages of ``frames`` frame sets climbing a 60 x 60 x 100 mm tower."""
    cal = make_calibration()
    msgs, t, counter = [], 1.0, 0
    per_line = 60
    n_lines = max(1, frames // per_line)
    for k in range(n_lines):
        z = 100.0 * k / max(n_lines - 1, 1)
        scene = Scene(boxes=[((30, 30, -1), (90, 90, z))])
        y = 32 + (k * 7.0) % 56
        a, b = (30, y, z), (90, y, z)
        m, _ = raster_run(scene, cal, [(a, b) if k % 2 == 0 else (b, a)], step_mm=1.0,
                          t0_s=t, counter0=counter, noise_mm=0.05, seed=k)
        msgs += m
        t, counter = m[-1].stamp_s + 0.1, counter + per_line + 1
    return cal, msgs


def run_once(cal, msgs, measure_latency: bool, batch_profiles: int = REPLAY_BATCH_PROFILES,
             layer_every: int = 0, threads: int = 2, cfg: MonitorConfig | None = None):
    """One replay (package defaults unless ``cfg``); with ``layer_every`` > 0 the surface is
    extracted every that many profiles (like a layer end) and the extraction times are returned
    instead of latencies."""
    mon = TsdfFusion(cal, cfg or MonitorConfig(), ProcessConfig(), batch_profiles=batch_profiles)
    mon.tsdf.threads = threads
    lat, acc = [], 0.0
    t0 = time.perf_counter()
    if measure_latency:
        for m in msgs:
            s = time.perf_counter()
            before = mon.profiles_fused
            mon.feed(m)
            acc += time.perf_counter() - s
            if mon.profiles_fused != before:  # a frame set was fused: its total cost
                lat.append(acc)
                acc = 0.0
    elif layer_every:
        for m in msgs:
            mon.feed(m)
            if isinstance(m, Profile) and m.counter % layer_every == layer_every - 1 \
                    and m.sensor_id == "S3":
                s = time.perf_counter()
                mon.surface()
                lat.append(time.perf_counter() - s)
    else:
        for m in msgs:
            mon.feed(m)
    mon.surface() if layer_every else mon._flush()
    elapsed = time.perf_counter() - t0
    return mon, elapsed, lat


def numpy_baseline(origins, points, voxel, trunc):
    """The same projective update with numpy scatter into a dense grid (samples per voxel)."""
    d = points - origins
    r = np.linalg.norm(d, axis=1, keepdims=True)
    u = d / r
    offs = np.arange(-trunc, trunc + 1e-9, voxel)
    lo = points.min(0) - 2 * trunc
    shape = np.ceil((points.max(0) + 2 * trunc - lo) / voxel).astype(int) + 1
    acc = np.zeros(np.prod(shape))
    wsum = np.zeros(np.prod(shape))
    for o in offs:
        p = points + u * o
        idx = np.floor((p - lo) / voxel).astype(np.int64)
        flat = np.ravel_multi_index(idx.T, shape)
        np.add.at(acc, flat, -o)
        np.add.at(wsum, flat, 1.0)
    return acc, wsum


def static_error(cal, msgs, cfg: MonitorConfig, sdf) -> tuple[float, float, int]:
    """RMS and p95 [mm] of ``|sdf|`` at the vertices of the surface ours fuses from ``msgs``
    with ``cfg``, and their number (:func:`open3d_peer.surface_error`)."""
    mon = run_once(cal, msgs, False, cfg=cfg)[0]
    return open3d_peer.surface_error(
        SurfaceExtractor(mon.tsdf, cfg.min_weight).update().vertices_O, sdf)


def peer(cal, msgs, repeats: int) -> None:
    """Open3D's VoxelBlockGrid on the same stream: speed, extraction and accuracy beside ours."""
    cfg = MonitorConfig()
    profiles = open3d_peer.synced_profiles(cal, msgs, cfg.max_pose_gap_s, cfg.reorder_window_s)
    rates, ours, merged, o3d_field = [], [], [], None
    scans: dict[str, list[float]] = {"scan": [], "scan_merged": []}
    for _ in range(repeats):  # interleaved with ours, so both see the same machine load
        o3d_field, dt = open3d_peer.open3d_run(profiles, cfg.voxel_mm, cfg.truncation_voxels)
        rates.append(o3d_field.points / dt)
        mon, elapsed, _ = run_once(cal, msgs, False)
        ours.append(mon.points_fused / elapsed)
        mon, elapsed, _ = run_once(cal, msgs, False, cfg=MERGED)
        merged.append(mon.points_fused / elapsed)
        for key, scan_cfg in (("scan", SCAN), ("scan_merged", SCAN_MERGED)):
            mon, elapsed, _ = run_once(cal, msgs, False, cfg=scan_cfg)
            scans[key].append(mon.points_fused / elapsed)
    o3d_rate, ours_pts_s = statistics.median(rates), statistics.median(ours)
    print(f"Open3D VoxelBlockGrid on the same stream ({os.environ['OMP_NUM_THREADS']} threads, "
          f"{cfg.voxel_mm} mm voxels, +-{cfg.truncation_voxels:g} voxels, 8^3 blocks, one depth "
          f"image per profile, poses given), median of {repeats}: {o3d_rate / 1e6:.2f} M "
          f"points/s; ours end to end (sync + registration + TSDF, batched, 2 threads), "
          f"interleaved with it: {ours_pts_s / 1e6:.2f} M points/s: ratio "
          f"{ours_pts_s / o3d_rate:.2f}x; with [monitor] ray_merge_voxels = "
          f"{MERGED.ray_merge_voxels} (neighbouring points as one ray): "
          f"{statistics.median(merged) / 1e6:.2f} M points/s: ratio "
          f"{statistics.median(merged) / o3d_rate:.2f}x")
    scan, scan_merged = (statistics.median(scans[k]) for k in ("scan", "scan_merged"))
    print(f"like for like with Open3D (a scan, spray off: no deposit cap, weights averaged up "
          f"to 1e4; accuracy on the static scene below), interleaved with it: "
          f"{scan / 1e6:.2f} M points/s: ratio {scan / o3d_rate:.2f}x; with ray_merge_voxels "
          f"{SCAN_MERGED.ray_merge_voxels}: {scan_merged / 1e6:.2f} M points/s: ratio "
          f"{scan_merged / o3d_rate:.2f}x")
    mon = run_once(cal, msgs, False)[0]
    ours_t, o3d_t = [], []
    # not interleaved: Open3D's OpenMP threads spin-wait after each call and took a core from
    # ours (an extraction timed between Open3D's took twice as long as alone); they are given
    # time to go idle first
    time.sleep(OPENMP_IDLE_S)
    ext_repeats = max(repeats, EXTRACTION_REPEATS)  # a fraction of a second each, and noisy
    for _ in range(ext_repeats):
        t = time.perf_counter()
        surf = SurfaceExtractor(mon.tsdf, cfg.min_weight).update()
        ours_t.append(time.perf_counter() - t)
    for _ in range(ext_repeats):
        t = time.perf_counter()
        v_o3d, _ = o3d_field.extract(cfg.min_weight)
        o3d_t.append(time.perf_counter() - t)
    a, b = statistics.median(ours_t), statistics.median(o3d_t)
    print(f"surface extraction from scratch of that stream, median of {ext_repeats}: ours "
          f"{a:.3f} s ({surf.n_vertices} vertices), Open3D {b:.3f} s ({len(v_o3d)} vertices): "
          f"ratio {b / a:.2f}x")
    scene = Scene(boxes=[((40, 40, -1), (80, 80, 10))], spheres=[((60, 60, 10), 8.0)])
    smsgs, _ = raster_run(scene, cal, raster_lines((35, 85), np.arange(35, 86, 2.0), 10.0),
                          step_mm=1.0, noise_mm=0.05, seed=3)
    mon = run_once(cal, smsgs, False)[0]
    ours_merged, ours_still, scan_merged_err = (static_error(cal, smsgs, c, scene.sdf)
                                                for c in (MERGED, SCAN, SCAN_MERGED))
    sprof = open3d_peer.synced_profiles(cal, smsgs, cfg.max_pose_gap_s, cfg.reorder_window_s)
    o3d_static = open3d_peer.open3d_run(sprof, cfg.voxel_mm, cfg.truncation_voxels)[0]
    ours_t, o3d_t = [], []
    time.sleep(OPENMP_IDLE_S)
    for _ in range(ext_repeats):
        t = time.perf_counter()
        ours_v = SurfaceExtractor(mon.tsdf, cfg.min_weight).update().vertices_O
        ours_t.append(time.perf_counter() - t)
    for _ in range(ext_repeats):
        t = time.perf_counter()
        o3d_v, _ = o3d_static.extract(cfg.min_weight)
        o3d_t.append(time.perf_counter() - t)
    ours = open3d_peer.surface_error(ours_v, scene.sdf)
    theirs = open3d_peer.surface_error(o3d_v, scene.sdf)
    print(f"static box + sphere cap (noise 0.05 mm), accuracy against the analytic truth "
          f"(|sdf| at the vertices): ours RMS {ours[0]:.3f} mm, p95 {ours[1]:.3f} mm "
          f"({ours[2]} vertices; with the spray assumed off, no deposit cap and weights "
          f"averaged up to 1e4 like Open3D's: RMS {ours_still[0]:.3f} mm, p95 "
          f"{ours_still[1]:.3f} mm, {ours_still[2]} vertices, and with ray_merge_voxels "
          f"{SCAN_MERGED.ray_merge_voxels} too: RMS {scan_merged_err[0]:.3f} mm, p95 "
          f"{scan_merged_err[1]:.3f} mm, {scan_merged_err[2]} vertices; defaults with "
          f"ray_merge_voxels {MERGED.ray_merge_voxels}: RMS {ours_merged[0]:.3f} mm, p95 "
          f"{ours_merged[1]:.3f} mm, {ours_merged[2]} vertices); Open3D (grid shifted a quarter "
          f"voxel, open3d_peer) RMS {theirs[0]:.3f} mm, p95 {theirs[1]:.3f} mm "
          f"({theirs[2]} vertices); extraction from scratch, median of {ext_repeats}: ours "
          f"{statistics.median(ours_t):.3f} s, Open3D {statistics.median(o3d_t):.3f} s")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--frames", type=int, default=1200, help="frame sets (3 profiles each)")
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    load = " ".join(f"{x:.2f}" for x in os.getloadavg())
    print(f"load average (1, 5, 15 min): {load} on {os.cpu_count()} cores")
    t = time.perf_counter()
    cal, msgs = make_stream(args.frames)
    n_prof = sum(isinstance(m, Profile) for m in msgs)
    print(f"stream: {len(msgs)} messages, {n_prof} profiles, cast in "
          f"{time.perf_counter() - t:.1f} s")
    run_once(cal, msgs[:2000], False)  # JIT warm-up
    run_once(cal, msgs[:2000], False, batch_profiles=3)

    runs = {(REPLAY_BATCH_PROFILES, 2): [], (REPLAY_BATCH_PROFILES, 1): [], (3, 2): []}
    mon = None
    for _ in range(args.repeats):
        for bp, th in runs:  # interleaved, so all see the same machine load
            mon, elapsed, _ = run_once(cal, msgs, False, batch_profiles=bp, threads=th)
            runs[bp, th].append(mon.points_fused / elapsed)
    new, one, old = (statistics.median(v) for v in runs.values())
    print(f"end-to-end fusion (sync + registration + TSDF), median of {args.repeats}: "
          f"{new / 1e6:.2f} M points/s batched (batch_profiles={REPLAY_BATCH_PROFILES}, "
          f"2 threads); {one / 1e6:.2f} M points/s batched with the 1-thread kernel (ratio "
          f"{new / one:.2f}x); {old / 1e6:.2f} M points/s one frame set per call "
          f"(batch_profiles=3, serial below {MIN_SPLIT_POINTS} points; ratio {new / old:.2f}x) "
          f"({mon.points_fused} points, {mon.tsdf.n_blocks} blocks, voxel {mon.cfg.voxel_mm} mm)")

    peer(cal, msgs, args.repeats)
    growing_part.compare(cal, args.repeats, run_once,
                         {"ours, defaults": None, "ours, merged rays": MERGED,
                          "ours, scan (spray off)": SCAN, "ours, scan, merged rays": SCAN_MERGED})

    c = time.process_time()
    run_once(cal, msgs, False, threads=1)
    cpu_serial = time.process_time() - c
    c = time.process_time()
    mon = run_once(cal, msgs, False, threads=2)[0]
    cpu_split = time.process_time() - c
    alloc, t0, t1, threaded = mon.tsdf.split_cpu_s
    crit = cpu_split - t0 - t1 + threaded  # the replay's critical path on two idle cores
    print(f"CPU time of one batched replay (load-independent): {cpu_serial:.2f} s with the "
          f"1-thread kernel; 2 threads: {cpu_split:.2f} s in all, of it committing staged TSDF "
          f"blocks {alloc:.2f} s (serial), thread 0 {t0:.2f} s, thread 1 {t1:.2f} s (each its "
          f"own block columns; the slower of each batch {threaded:.2f} s) -> critical path "
          f"{crit:.2f} s = {mon.points_fused / crit / 1e6:.2f} M points/s end to end on two "
          f"idle cores (1 thread: {mon.points_fused / cpu_serial / 1e6:.2f} M points/s)")

    _, _, lat = run_once(cal, msgs, True, batch_profiles=3)
    lat_ms = np.array(lat) * 1e3
    print(f"per-frame-set latency, live (batch_profiles=3: 3 x 640 points + robot states): "
          f"p50 {np.percentile(lat_ms, 50):.2f} ms, p99 {np.percentile(lat_ms, 99):.2f} ms, "
          f"max {lat_ms.max():.2f} ms over {len(lat_ms)} frame sets")

    every = 60  # a surface every 60 frame sets (6 s of stream), like a layer end
    _, _, ext = run_once(cal, msgs, False, layer_every=every)
    ext_ms = np.array(ext) * 1e3
    print(f"incremental surface per layer (every {every} frame sets, touched chunks only): "
          f"p50 {np.percentile(ext_ms, 50):.0f} ms, max {ext_ms.max():.0f} ms over "
          f"{len(ext_ms)} layers")
    mon = run_once(cal, msgs, False, batch_profiles=REPLAY_BATCH_PROFILES)[0]
    t = time.perf_counter()
    surf = SurfaceExtractor(mon.tsdf, mon.cfg.min_weight).update()  # a new one meshes all
    print(f"surface extraction from scratch (all {mon.tsdf.n_blocks} blocks): "
          f"{time.perf_counter() - t:.2f} s, {surf.n_vertices} vertices")

    # kernel alone against a numpy scatter baseline, same rays
    rng = np.random.default_rng(0)
    n = 400_000
    pts = np.column_stack([rng.uniform(30, 90, n), rng.uniform(30, 90, n), np.full(n, 50.0)])
    org = pts + np.array([0.0, -54.5, 77.8])
    kts = {2: [], 1: []}
    fields = {th: SparseTSDF(0.5, 1.5, 8.0, threads=th) for th in kts}
    for tsdf in fields.values():
        tsdf.integrate(org, pts)
    for _ in range(args.repeats):
        for th, tsdf in fields.items():
            s = time.perf_counter()
            tsdf.integrate(org, pts)
            kts[th].append(time.perf_counter() - s)
    kt, kt1 = kts[2], kts[1]
    bt = []
    for _ in range(args.repeats):
        s = time.perf_counter()
        numpy_baseline(org, pts, 0.5, 1.5)
        bt.append(time.perf_counter() - s)
    k_rate, b_rate = n / statistics.median(kt), n / statistics.median(bt)
    k1_rate = n / statistics.median(kt1)
    print(f"TSDF kernel alone: {k_rate / 1e6:.2f} M points/s with 2 threads, "
          f"{k1_rate / 1e6:.2f} M points/s with 1 (ratio {k_rate / k1_rate:.2f}x); numpy "
          f"scatter baseline {b_rate / 1e6:.2f} M points/s; ratio {k_rate / b_rate:.1f}x")

    tracemalloc.start()
    mon, _, _ = run_once(cal, msgs, False)
    mon.surface()
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    print(f"peak traced memory of one run incl. surface: {peak / 2**20:.1f} MiB "
          f"(TSDF arrays {mon.tsdf.nbytes() / 2**20:.1f} MiB); process max RSS "
          f"{resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MiB")


if __name__ == "__main__":
    main()
