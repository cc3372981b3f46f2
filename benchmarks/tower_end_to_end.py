"""The twisted tower end to end: ``dm2 run twisted_tower --no-record`` in a child process, then
its stage times, real-time factor, peak RSS, track count (and the area of the tracked regions
summed over the layers, per kind: what was flagged and tracked, however the regions were
grouped into tracks) and the reconstruction per layer band against the twin's true surface.

Printed (``--runs`` runs of ``dm2 run``, 3 by default: each run's wall time, peak RSS and the
load average after it; the wall time below is their median, the peak RSS their maximum; stage
times, tracks and the reconstruction are the last run's, kept with ``--out``):

- the CPU model, the number of cores and the load average before and after the run (the
  machine may be shared: timings are only comparable at a similar load);
- per stage wall time [s] from ``report.json`` (fusion, which holds the reference and layer
  analysis a layer end triggers inside ``TsdfFusion.feed``, and fusion net of the analysis;
  reference, layer analysis, real-time deviation; the run before the report, twin included;
  "report + start-up" is the rest of the child's wall time: writing the report folder,
  interpreter start and imports), the real-time factor (process seconds over
  wall seconds) and the child's peak RSS (``wait4``);
- per band of ``--band`` layers, over all written (observed) vertices of the band's layer
  meshes (``meshes/layer_NNN.ply``), each against the twin's true surface when that layer
  closed (``truth/layer_NNN.ply``), inside the truth's xy extent less 1 mm (as ``dm2 run``
  measures it): RMS and p95 of the unsigned distance [mm], and the coverage: the share of the
  true surface's vertices over built cells (height above 1 um) that have a written vertex
  within ``--cover-mm`` (default 1 mm, two voxels), mean over the band's layers; and, beside
  them, the share of those vertices that stood still for ``--stale-layers`` layers (bit-identical
  to a vertex of that many layers' earlier mesh: no profile has touched their voxels since, e.g.
  ledges far below the top of a tall part), the RMS over them and over the others (the surface
  the profilers still see), so that what the TSDF could not follow is told from what it got wrong;
  and the RMS of the stale vertices against the true surface of ``--stale-layers`` layers
  earlier ("then", when they were already written as they are): a stale vertex far from the
  truth now but near it then lies where the true surface moved while no profile looked there
  (on the twin, overspray that later layers' tilted contour jets put on the walls below);
- the track count of the report, and per track, over all its layers, the vertices its regions
  flagged (report.json ``track_truth``): their median deviation from the reference and their
  median and p90 distance from the twin's true surface (a distance far below the deviation:
  the twin's true part stands off the reference there as measured, so the track reports the
  part, not a measurement error).

    .venv/bin/python benchmarks/tower_end_to_end.py [--duration S] [--runs 3] [--band 8] [--out DIR]
    .venv/bin/python benchmarks/tower_end_to_end.py --analyse DIR   (a folder kept with --out)
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
BUILT_MM = 1e-3        # a truth cell with material (as twin.world.truth.write_layer_surface)
UNOBSERVED = 5.0       # dm2.defects.classify.CLASS_NAMES.index("unobserved")
SAME_MM = 1e-4         # a vertex this close to an earlier mesh's vertex stood still


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def load_avg() -> str:
    return " ".join(f"{x:.2f}" for x in os.getloadavg())


SIDECAR_HEADER = "# written by benchmarks/tower_end_to_end.py\n"


def sidecar(run_dir: Path, suffix: str) -> Path:
    """The file ``<run_dir><suffix>`` beside the run folder (the child's log, the wall time) that
    this script may write: new, or written by it before (its first line is
    ``SIDECAR_HEADER``); a file of any other origin there stops the benchmark, untouched."""
    path = run_dir.parent / f"{run_dir.name}{suffix}"
    if path.exists():
        with open(path, errors="replace") as f:
            if f.readline() != SIDECAR_HEADER:
                raise SystemExit(f"{path}: exists and was not written by this benchmark; move it "
                                 "or choose another --out")
    return path


def run_child(args, run_dir: Path) -> tuple[float, float, int]:
    """``(wall_s, peak_rss_mib, returncode)`` of ``dm2 run`` into ``run_dir``; its output goes
    to the sidecar ``<run_dir>.log``."""
    cmd = [sys.executable, "-m", "dm2.cli.main", "run", args.scenario, "--no-record",
           "--out", str(run_dir)]
    if args.duration is not None:
        cmd += ["--duration", str(args.duration)]
    env = {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    t0 = time.perf_counter()
    with open(sidecar(run_dir, ".log"), "w") as log:
        log.write(SIDECAR_HEADER)
        log.flush()
        proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=log, stderr=subprocess.STDOUT)
        _, status, usage = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    return time.perf_counter() - t0, usage.ru_maxrss / 1024.0, proc.returncode


def observed_vertices(run_dir: Path, layer: int):
    """Observed vertices ``(n, 3)`` [mm] of one layer's mesh, or None without the file."""
    from dm2.report.meshes import read_ply_vertex_fields

    mesh_path = run_dir / "meshes" / f"layer_{layer:03d}.ply"
    if not mesh_path.exists():
        return None
    f = read_ply_vertex_fields(mesh_path)
    v = np.column_stack([f["x"], f["y"], f["z"]]).astype(np.float64)
    return v[f["scalar_class"] != UNOBSERVED]


def true_surface(run_dir: Path, layer: int):
    """``(vertices (n, 3) [mm], faces)`` of the twin's true surface when ``layer`` closed, or
    None without the file."""
    from dm2.io.ply import read_mesh_ply

    path = run_dir / "truth" / f"layer_{layer:03d}.ply"
    if not path.exists():
        return None
    fields, faces = read_mesh_ply(path)
    return np.column_stack([fields[k] for k in "xyz"]).astype(np.float64), faces


def layer_errors(run_dir: Path, layer: int, cover_mm: float, stale_layers: int):
    """``(distances (n,), covered share, stale (n,) bool, distances then (n,))`` of one layer,
    or None without its files; ``stale``: the vertex is bit-identical to one ``stale_layers``
    layers earlier; ``distances then``: a stale vertex's distance to the true surface of that
    earlier layer (NaN for the others), so a truth that moved under a vertex no profile has
    touched since is told from a vertex the TSDF got wrong."""
    from scipy.spatial import cKDTree

    from dm2.bench.reconstruction import CROP_MM, mesh_distance

    truth = true_surface(run_dir, layer)
    v = observed_vertices(run_dir, layer)
    if truth is None or v is None:
        return None
    tv, faces = truth
    lo, hi = tv[:, :2].min(axis=0) + CROP_MM, tv[:, :2].max(axis=0) - CROP_MM
    v = v[np.all((v[:, :2] >= lo) & (v[:, :2] <= hi), axis=1)]
    d = mesh_distance(v, tv, faces)  # (as dm2 run's own reconstruction check)
    inside = np.all((tv[:, :2] >= lo) & (tv[:, :2] <= hi), axis=1)
    built = tv[inside & (np.abs(tv[:, 2]) > BUILT_MM)]
    if len(v) and len(built):
        near, _ = cKDTree(v).query(built, distance_upper_bound=cover_mm)
        covered = float(np.mean(np.isfinite(near)))
    else:
        covered = 0.0
    stale = np.zeros(len(v), bool)
    d_then = np.full(len(v), np.nan)
    earlier = observed_vertices(run_dir, layer - stale_layers) if layer >= stale_layers else None
    if earlier is not None and len(earlier) and len(v):
        gap, _ = cKDTree(earlier).query(v, distance_upper_bound=SAME_MM)
        stale = np.isfinite(gap)
        then = true_surface(run_dir, layer - stale_layers) if stale.any() else None
        if then is not None:
            d_then[stale] = mesh_distance(v[stale], *then)
    return d, covered, stale, d_then


def track_truth_lines(rep: dict) -> list[str]:
    """Per track, from report.json's ``track_truth`` (dm2.bench.reconstruction.truth_checks,
    over all the track's layers): its flagged vertices' median deviation from the reference and
    their median (p90) distance from the twin's true surface. A distance far below the
    deviation says the twin's true part stands off the reference there as measured: the track
    reports the part, not a measurement error."""
    vs_truth = rep.get("track_truth", {})
    lines = []
    for t in rep.get("tracks", []):
        c = vs_truth.get(str(t["id"]))
        if c is None:
            continue
        lines.append(f"  track {t['id']} ({t['kind']}, layers {t['first_layer']}-"
                     f"{t['last_layer']}): {c['n_vertices']} flagged vertices: deviation from "
                     f"the reference median {c['deviation_median_mm']:+.2f} mm; distance from "
                     f"the twin's true surface median {c['truth_distance_median_mm']:.2f} mm, "
                     f"p90 {c['truth_distance_p90_mm']:.2f} mm"
                     + ("; the part itself deviates" if c["part_deviates"] else ""))
    return lines


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="twisted_tower")
    ap.add_argument("--duration", type=float, default=None, help="process seconds to run")
    ap.add_argument("--band", type=int, default=8, help="layers per band")
    ap.add_argument("--cover-mm", type=float, default=1.0)
    ap.add_argument("--stale-layers", type=int, default=16,
                    help="a vertex unchanged for this many layers counts as stale")
    ap.add_argument("--runs", type=int, default=3,
                    help="runs of dm2 run: median wall time, maximum peak RSS")
    ap.add_argument("--out", type=Path, default=None,
                    help="keep the last run's folder here (its log and wall time beside it: "
                    "<out>.log, <out>.wall)")
    ap.add_argument("--analyse", type=Path, default=None, metavar="RUN_DIR",
                    help="only print the figures of a run folder this script kept with --out")
    args = ap.parse_args()
    if args.analyse is not None:
        log = sidecar(args.analyse, ".wall")
        wall, rss = (float(x) for x in log.read_text().splitlines()[1].split()) \
            if log.exists() else (0.0, 0.0)
        report(args.analyse, wall, rss, args)
        return
    print(f"CPU: {cpu_model()}, {os.cpu_count()} cores; load average before: {load_avg()}")
    tmp = None
    if args.out is None:
        tmp = Path(tempfile.mkdtemp(prefix="dm2-tower-"))
        run_dir = tmp / "run"
    else:
        run_dir = args.out.absolute()
        run_dir.parent.mkdir(parents=True, exist_ok=True)
        for suffix in (".log", ".wall"):  # before any run: refuse a user's file there
            sidecar(run_dir, suffix)
    try:
        walls, rss_all = [], []
        for k in range(max(args.runs, 1)):
            last = k == max(args.runs, 1) - 1
            scratch = None if last else Path(tempfile.mkdtemp(prefix="dm2-tower-run-"))
            target = run_dir if last else scratch / "run"
            wall, rss_mib, rc = run_child(args, target)
            if rc != 0:
                log = sidecar(target, ".log").read_text()[-3000:]
                raise SystemExit(f"dm2 run failed (exit {rc}):\n{log}")
            print(f"run {k + 1}/{max(args.runs, 1)}: wall {wall:.1f} s, peak RSS {rss_mib:.0f} "
                  f"MiB; load average after: {load_avg()}")
            walls.append(wall)
            rss_all.append(rss_mib)
            if scratch is not None:
                shutil.rmtree(scratch, ignore_errors=True)
        wall, rss_mib = statistics.median(walls), max(rss_all)
        sidecar(run_dir, ".wall").write_text(f"{SIDECAR_HEADER}{wall} {rss_mib}\n")
        report(run_dir, wall, rss_mib, args)
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)


def report(run_dir: Path, wall: float, rss_mib: float, args) -> None:
    rep = json.loads((run_dir / "report.json").read_text())
    t = rep["timing"]
    process_s = float(t["simulated_process_s"])
    # a layer end inside TsdfFusion.feed runs that layer's reference and analysis: the session's
    # fusion time holds them; "fusion, net" takes the layer analysis out
    stages = {"fusion (with nested layer ends)": t["fusion_s"],
              "fusion, net of layer analysis": t["fusion_s"] - t["analysis_s"],
              "reference": t["reference_s"], "layer analysis": t["analysis_s"],
              "real-time deviation": t["realtime_s"],
              "run before the report": t["wall_s"]}
    if wall > 0:
        stages["report + start-up"] = wall - t["wall_s"]
    n_layers = len(rep.get("layers", []))
    if wall > 0:
        print(f"{args.scenario}: {process_s:.0f} s of process, {n_layers} layers; dm2 run wall "
              f"(median) "
              f"{wall:.1f} s = {process_s / wall:.1f}x real time; peak RSS {rss_mib:.0f} MiB")
    else:  # a folder not written by this script: no child wall time or RSS
        wall = t["wall_s"]
        print(f"{args.scenario}: {process_s:.0f} s of process, {n_layers} layers; run wall "
              f"before the report {wall:.1f} s = {process_s / wall:.1f}x real time")
    for name, s in stages.items():
        extra = f" ({s / max(n_layers, 1):.2f} s per layer)" if name == "layer analysis" else ""
        print(f"  {name:>32s}: {s:7.1f} s{extra}")
    # the tracked area over all layers does not depend on how regions are grouped into tracks
    tracked: dict[str, float] = {}
    for lay in rep.get("layers", []):
        for reg in lay.get("regions", []):
            if reg.get("track_id") is not None:
                tracked[reg["kind"]] = tracked.get(reg["kind"], 0.0) + float(reg["area_mm2"])
    print(f"tracks: {len(rep.get('tracks', []))}; area in tracked regions, summed over the "
          "layers: " + (", ".join(f"{k} {v:.0f} mm2" for k, v in sorted(tracked.items()))
                        or "none"))
    print("each track against the twin's truth (its flagged vertices: deviation from the "
          "reference, and how far they lie from the true surface):")
    for line in track_truth_lines(rep):
        print(line)
    layers = sorted(int(k) for k in rep.get("reconstruction", {}))
    print(f"reconstruction per {args.band}-layer band (all written vertices vs the twin's true "
          f"surface at each layer's end; coverage: true built surface within {args.cover_mm:g} "
          "mm of a written vertex)")
    print(f"{'layers':>9} {'RMS mm':>7} {'p95 mm':>7} {'max mm':>7} {'cover':>6} {'vertices':>9}"
          f" {'stale':>6} {'RMS stale':>9} {'then':>6} {'RMS rest':>8}   (stale: unchanged for "
          f"{args.stale_layers} layers; then: the stale vertices against the true surface of "
          f"{args.stale_layers} layers earlier)")
    worst = [0.0, 0.0, 1.0]
    for b0 in range(0, (max(layers) + 1) if layers else 0, args.band):
        ds, cov, stale, then = [], [], [], []
        for k in range(b0, b0 + args.band):
            r = layer_errors(run_dir, k, args.cover_mm, args.stale_layers)
            if r is not None:
                ds.append(r[0])
                cov.append(r[1])
                stale.append(r[2])
                then.append(r[3])
        if not ds:
            continue
        d, old, d_then = np.concatenate(ds), np.concatenate(stale), np.concatenate(then)
        rms, p95, c = float(np.sqrt(np.mean(d ** 2))), float(np.percentile(d, 95)), \
            float(np.mean(cov))
        rms_stale, rms_then, rms_rest = (float(np.sqrt(np.mean(x ** 2))) if x.size else
                                         float("nan") for x in (d[old], d_then[old], d[~old]))
        worst = [max(worst[0], rms), max(worst[1], p95), min(worst[2], c)]
        print(f"{b0:4d}-{b0 + len(ds) - 1:<4d} {rms:7.3f} {p95:7.3f} {d.max():7.2f} "
              f"{100 * c:5.1f}% {d.size:9d} {100 * old.mean():5.1f}% {rms_stale:9.3f} "
              f"{rms_then:6.3f} {rms_rest:8.3f}")
    print(f"worst band: RMS {worst[0]:.3f} mm, p95 {worst[1]:.3f} mm, coverage "
          f"{100 * worst[2]:.1f}% (targets: <= 0.25 mm, <= 0.5 mm, >= 95 %)")


if __name__ == "__main__":
    main()
