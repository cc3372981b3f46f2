"""The twisted tower's scale: how tall and how heavy the twin builds it against the plan.

Runs the scenario's toolpath and executed motion, then grows the true part with the twin's
deposition only (no profilers, no recording: the same ``SprayModel.plan_samples`` /
``deposit_plan`` calls as :class:`twin.stream.simulate.Simulation`, so the surface is the twin's
own;
the scenario's faults are not applied), and prints per layer band:

- planned top ``z`` of the band's last layer and the true height there: at the part's centre
  (mean over a 4 mm disc), the median over the layer's planned region, the median over its
  interior (inset 5 mm) and its edge ring (the outer 3 mm);
- mean layer height of the band (centre and median), mass deposited and fed [g] (deposited /
  fed is the overall efficiency), share of the band's time at programmed speed vs executed;

then the final height (centre, median of the top region, median of its supported part = the
cells every layer's planned region covers, max) in mm, the mass in g (all of it, and the part
within 3 mm of its planned footprint, i.e. without the overspray on the plate), the executed
against the programmed time of each move kind, and the wall time of each stage.

The edge jet comes from the scenario (``toolpath.contour_jet``); ``--set
toolpath.contour_jet=away_from_wall`` shows the tower with the jet pointing away from the wall.

    .venv/bin/python benchmarks/tower_scale.py [--scenario twisted_tower] [--layers N]
        [--band 8] [--set process.feed_g_min=30]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

_HERE = Path(__file__).resolve().parent
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != _HERE]
sys.path.insert(0, str(_HERE.parent))

import numpy as np  # noqa: E402
import shapely  # noqa: E402

from dm2.core.config import load_scenario, parse_scenario  # noqa: E402
from dm2.core.messages import KIND_CODE  # noqa: E402
from scenarios import resolve_scenario  # noqa: E402

CENTRE_RADIUS_MM = 2.0
INTERIOR_INSET_MM = 5.0
EDGE_RING_MM = 3.0


def _scenario(name: str, layers: int | None, overrides: list[str]):
    sc = load_scenario(resolve_scenario(name))
    data = sc.to_toml_dict()
    if layers is not None:
        data.setdefault("toolpath", {})["max_layers"] = layers
    for item in overrides:
        key, _, value = item.partition("=")
        *path, leaf = key.strip().split(".")
        node = data
        for p in path:
            node = node.setdefault(p, {})
        try:
            node[leaf] = float(value) if "." in value or value.isdigit() else value
        except ValueError:
            node[leaf] = value
    return parse_scenario(data, f"{name} (overridden)")


def _masks(region, xg, yg):
    inside = shapely.contains_xy(region, xg, yg)
    core = region.buffer(-INTERIOR_INSET_MM)
    interior = shapely.contains_xy(core, xg, yg) if not core.is_empty else np.zeros_like(inside)
    ring_in = region.buffer(-EDGE_RING_MM)
    edge = inside & ~(shapely.contains_xy(ring_in, xg, yg) if not ring_in.is_empty
                      else np.zeros_like(inside))
    c = region.centroid
    centre = (xg - c.x) ** 2 + (yg - c.y) ** 2 <= CENTRE_RADIUS_MM ** 2
    return inside, interior, edge, centre


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="twisted_tower")
    ap.add_argument("--layers", type=int, default=None, help="build only the first N layers")
    ap.add_argument("--band", type=int, default=8, help="layers per printed band")
    ap.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE")
    args = ap.parse_args()
    print(f"load average: {' '.join(f'{v:.2f}' for v in os.getloadavg())}")

    from dm2.toolpath.slicing import slice_mesh
    from twin.stream.simulate import Simulation
    from twin.world.deposition import SprayModel
    from twin.world.heightfield import HEIGHTFIELD_CELL_MM, HeightField

    sc = _scenario(args.scenario, args.layers, args.set)
    t0 = time.perf_counter()
    sim = Simulation(sc)
    tp, motion = sim.toolpath, sim.motion
    t_setup = time.perf_counter() - t0
    sliced = slice_mesh(sim.part_mesh_O, sc.toolpath.layer_mm, sc.toolpath.max_layers)
    z_plan = sliced.layer_z_mm() + sc.toolpath.layer_mm  # top of each layer
    plate = sc.cell.plate_size_mm
    hf = HeightField((plate[0], plate[1]), HEIGHTFIELD_CELL_MM, plate[2])
    spray = SprayModel(sc.process, seed=sc.seed)
    xg, yg = np.meshgrid(*hf.centres_mm())
    dt = motion.dt_s
    plan = spray.plan_samples(motion.position_O, motion.axis_O, dt, spray_on=motion.spray_on)
    layer = motion.layer
    starts = np.r_[0, np.flatnonzero(np.diff(layer)) + 1, layer.size]
    rho = sc.process.powder_density_g_cm3 / 1000.0  # g/mm^3
    # programmed time per sample: arc length advanced over programmed speed of its move
    ds = np.r_[0.0, np.diff(motion.arc_mm)]
    t_prog = ds / tp.speed_mm_s[motion.segment]

    print(f"{sc.name}: {tp.n_layers} layers, {len(tp)} toolpath points, {motion.duration_s:.0f} s "
          f"of process time ({len(motion)} samples); feed {sc.process.feed_g_min:g} g/min; "
          f"setup (part, toolpath, motion) {t_setup:.1f} s")
    print(f"{'layers':>9} {'z_plan':>6} {'centre':>6} {'median':>6} {'inter.':>6} {'edge':>6} "
          f"{'dz_c':>5} {'dz_med':>6} {'dep_g':>6} {'fed_g':>6} {'eff':>5} "
          f"{'t_exec':>6} {'prog':>5} {'edge_t':>6}")
    t1 = time.perf_counter()
    band_start = 0
    prev_c = prev_m = 0.0
    dep0 = fed0 = 0.0
    for a, b in zip(starts[:-1], starts[1:], strict=True):
        k = int(layer[a])
        spray.deposit_plan(hf, plan, int(a), int(b))
        last = (k + 1) % args.band == 0 or b == layer.size
        if not last:
            continue
        inside, interior, edge, centre = _masks(sliced.regions[k], xg, yg)
        H = hf.heights_mm
        c, m = float(H[centre].mean()), float(np.median(H[inside]))
        hi = float(np.median(H[interior])) if interior.any() else float("nan")
        he = float(np.median(H[edge]))
        n_band = k + 1 - band_start
        sel = (layer >= band_start) & (layer <= k)
        t_exec = float(sel.sum() * dt)
        prog = float(t_prog[sel].sum()) / t_exec
        edge_t = float(((motion.kind == KIND_CODE["edge"]) & sel).sum() * dt) / t_exec
        dep = spray.deposited_volume_mm3 * rho - dep0
        fed = spray.fed_volume_mm3 * rho - fed0
        print(f"{band_start:4d}-{k:<4d} {z_plan[k]:6.1f} {c:6.1f} {m:6.1f} {hi:6.1f} {he:6.1f} "
              f"{(c - prev_c) / n_band:5.2f} {(m - prev_m) / n_band:6.2f} {dep:6.1f} {fed:6.1f} "
              f"{dep / max(fed, 1e-12):5.2f} {t_exec:6.0f} {prog:5.2f} {edge_t:6.2f}")
        band_start, prev_c, prev_m = k + 1, c, m
        dep0, fed0 = spray.deposited_volume_mm3 * rho, spray.fed_volume_mm3 * rho
    t_dep = time.perf_counter() - t1
    k = tp.n_layers - 1
    inside, _, _, centre = _masks(sliced.regions[k], xg, yg)
    column = shapely.intersection_all(sliced.regions)
    supported = shapely.contains_xy(column, xg, yg) & inside
    footprint = shapely.contains_xy(shapely.union_all(sliced.regions).buffer(EDGE_RING_MM), xg, yg)
    H = hf.heights_mm
    mass = spray.deposited_volume_mm3 * rho
    part_g = float(np.maximum(H[footprint], 0.0).sum()) * hf.cell_mm ** 2 * rho
    print(f"final: planned {z_plan[k]:.1f} mm; centre {H[centre].mean():.1f} mm, median of the "
          f"top region {np.median(H[inside]):.1f} mm, of its supported part "
          f"{np.median(H[supported]):.1f} mm, max {H.max():.1f} mm")
    print(f"mass: {mass:.0f} g deposited ({part_g:.0f} g on the part's footprint, the rest "
          f"overspray on the plate) of {spray.fed_volume_mm3 * rho:.0f} g fed "
          f"({mass / max(spray.fed_volume_mm3 * rho, 1e-12):.2f})")
    for name, code in KIND_CODE.items():
        sel = motion.kind == code
        if sel.any():
            print(f"{name:>8s}: executed {sel.sum() * dt:7.0f} s, programmed "
                  f"{t_prog[sel].sum():7.0f} s ({sel.sum() * dt / t_prog[sel].sum():.2f}x)")
    print(f"wall time: setup {t_setup:.1f} s, deposition {t_dep:.1f} s "
          f"({motion.duration_s / t_dep:.0f}x real time)")


if __name__ == "__main__":
    main()
