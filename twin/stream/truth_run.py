"""Ground truth beside a twin run: the true top surface after each layer and each fault's
effect, measured against a fault-free run of the same scenario and seed."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def nominal_layer_heights(sim, last_segment: int, layers: list[int]) -> dict:
    """Heights (ny, nx) [mm] after each of ``layers`` of the fault-free run of ``sim`` (a
    :class:`twin.stream.simulate.Simulation`; same seed, no corner dwell), which stops where the
    faulty run's toolpath move ``last_segment`` ends."""
    from twin.cell.motion import execute_toolpath
    from twin.world.deposition import twin_spray_model
    from twin.world.heightfield import HEIGHTFIELD_CELL_MM, HeightField

    motion = sim.motion
    if any(f.kind == "corner_dwell" for f in sim.scenario.faults):
        motion = execute_toolpath(sim.toolpath, sim.cell, rate_hz=sim.cell.robot_state_hz,
                                  accel_mm_s2=sim.cell.accel_mm_s2)
    plate = sim.scenario.cell.plate_size_mm
    hf = HeightField(size_mm=(plate[0], plate[1]), cell_mm=HEIGHTFIELD_CELL_MM,
                     thickness_mm=plate[2])
    spray = twin_spray_model(sim.scenario)  # same [twin_process] and seed
    n = int(np.searchsorted(motion.segment, last_segment, side="right"))
    dt = 1.0 / sim.cell.robot_state_hz
    layer = np.asarray(motion.layer[:n])
    ends = np.flatnonzero(np.append(layer[1:] != layer[:-1], True)) + 1 if n else np.zeros(0)
    out, wanted, a = {}, set(layers), 0
    # one batched deposition per layer: the same bits as one deposit call per motion sample
    for b in ends.astype(int).tolist():
        spray.deposit_samples(hf, motion.position_O[a:b], motion.axis_O[a:b], dt,
                              spray_on=motion.spray_on[a:b])
        if int(layer[b - 1]) in wanted:
            out[int(layer[b - 1])] = hf.heights_mm.copy()
        a = b
    return out


class TruthWriter:
    """Ground truth beside a run: the true top surface after each layer (PLY in O),
    ``faults.json``, each fault's effect measured against a fault-free run with the same seed
    and ``[twin_process]``, and per layer the map of that effect (``deviation_LLL.npz``).
    Nothing already in the folder is removed here: ``dm2 simulate --truth`` clears an earlier
    run's truth through the folder's dm2 manifest (:mod:`dm2.report.outdir`), so a shorter run
    leaves no stale layer and a user's file of the same name is never deleted."""

    def __init__(self, truth_dir, sim):
        self.dir = Path(truth_dir)
        self.dir.mkdir(parents=True, exist_ok=True)
        self.sim = sim
        self.faulty: dict[int, np.ndarray] = {}

    def layer(self, hf, layer: int) -> None:
        from twin.world.truth import write_layer_surface

        write_layer_surface(hf, self.dir / f"layer_{layer:03d}.ply")
        self.faulty[layer] = hf.heights_mm.copy()

    def check_validity(self, hf, spray, planned_fed_mm3: float, blob_mm3: float,
                       last_layer: int) -> dict:
        """Check the final true surface and the run's mass balance
        (:func:`twin.world.validity.check_truth`) and write ``validity.json``."""
        import json

        from twin.world.validity import check_truth

        sc = self.sim.scenario
        H = hf.heights_mm
        layer_mm = sc.toolpath.layer_mm
        top = float(self.sim.part_mesh_O.bounds[1][2])
        out = check_truth(
            H, hf.cell_mm, sigma_mm=spray.sigma_mm(), layer_mm=layer_mm,
            critical_angle_deg=spray.process.critical_angle_deg,
            field_gain_mm3=float(H.sum()) * hf.cell_mm ** 2 - blob_mm3,
            stuck_mm3=spray.deposited_volume_mm3, fed_mm3=spray.fed_volume_mm3,
            planned_fed_mm3=planned_fed_mm3,
            planned_top_mm=min(top, (last_layer + 1) * layer_mm))
        (self.dir / "validity.json").write_text(json.dumps(out, indent=1), encoding="utf-8")
        return out

    def finish(self, last_segment: int) -> None:
        from twin.world.heightfield import HEIGHTFIELD_CELL_MM
        from twin.world.truth import write_deviation_maps, write_fault_truth

        sc = self.sim.scenario
        nominal = (nominal_layer_heights(self.sim, last_segment, sorted(self.faulty))
                   if sc.faults else self.faulty)
        write_fault_truth(self.dir / "faults.json", sc.faults, self.faulty, nominal,
                          toolpath=self.sim.toolpath, cell_mm=HEIGHTFIELD_CELL_MM,
                          area_threshold_mm=sc.monitor.delta_global_mm)
        write_deviation_maps(self.dir, self.faulty, nominal, HEIGHTFIELD_CELL_MM)
