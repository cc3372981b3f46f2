"""The twin's orchestrator: one scenario in, the pipeline's message stream out.

:class:`Simulation` builds the part, its toolpath, the cell and the robot's executed motion,
then :meth:`Simulation.messages` steps through the motion at the controller rate: it grows
the true part (Gaussian spray plus injected faults), reports each robot state (the reported
flange pose carries ``noise.robot_repeatability_mm``, the truth does not), marks layer starts,
fires the cascaded profiler triggers (each scan sees the plate pose interpolated at its own
stamp) and, at the end of each layer, writes the ground truth. :func:`iter_messages` is that
generator; :func:`simulate` records it to MCAP with the scenario, toolpath and calibration
attached, so replaying a recording gives the pipeline exactly what an in-process run gives.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dm2.core.config import ConfigError
from dm2.core.frames import PoseInterpolator
from dm2.core.messages import SENSOR_IDS, Calibration, LayerMark, Profile, RobotState
from dm2.core.toml_write import dump_toml
from twin.schema import TwinScenario
from twin.stream.replan import NextLayer, Replanner
from twin.stream.threads import ChunkWorker, FanSplit, chunk_runs
from twin.world.heightfield import HEIGHTFIELD_CELL_MM

log = logging.getLogger(__name__)

ROBOT_NOISE_SEED_OFFSET = 1_000_003
Progress = Callable[[float, float], None]  # (process seconds done, total process seconds)


@dataclass(frozen=True)
class SimulationResult:
    """What :func:`simulate` wrote.

    Attributes
    ----------
    out_path : the MCAP recording
    truth_dir : folder with per-layer ground truth, or None
    process_s : float [s], simulated process time covered
    counts : dict message kind -> number written (``Profile``, ``RobotState``, ``LayerMark``)
    n_layers : int, layers started within the simulated time
    calibration : the calibration handed to the pipeline (perturbed per the scenario)
    """

    out_path: Path
    truth_dir: Path | None
    process_s: float
    counts: dict
    n_layers: int
    calibration: Calibration


class Simulation:
    """Everything fixed before the clock starts (part, toolpath, cell, motion, models).

    Attributes
    ----------
    scenario : the scenario
    toolpath : dm2.core.messages.Toolpath in O
    cell : twin.cell.cell.CellModel (its profilers at ``true_T_B_S`` when that is given: a cell
        whose sensors stand off the scenario's nominal layout)
    motion : twin.cell.motion.ExecutedMotion (sampled at ``cell.robot_state_hz``)
    true_calibration, calibration : the cell's true calibration and the one the pipeline gets
    end_s : float [s], last process time simulated (``scenario.duration_s`` cuts it short)
    final_heightfield, spray_cpu_s, worker_cpu_s, worker_fan_share : after a stream has run to
        its end, its true field, the CPU seconds [s] its deposition took and those of all the
        worker thread's tasks (deposition and its share of the fans; both on the calling thread
        without ``scan_thread``), and the share of each fan the worker cast at the end
    """

    def __init__(self, scenario: TwinScenario, true_T_B_S: dict | None = None,
                 layer_pause_s: float = 0.0):
        from dm2.toolpath import generate_toolpath
        from scenarios.parts import build_part
        from twin.cell.cell import CellModel
        from twin.cell.motion import execute_toolpath
        from twin.world.faults import FaultSchedule, perturbed_calibration

        self.scenario = scenario
        plate = scenario.cell.plate_size_mm
        self.part_mesh_O = build_part(scenario.part, plate)
        self.toolpath = generate_toolpath(self.part_mesh_O, scenario.toolpath)
        self.layer_pause_s = float(layer_pause_s)
        if self.layer_pause_s > 0:  # the powder stops on the way to each layer, which waits
            starts = np.flatnonzero(np.diff(self.toolpath.layer)) + 1
            spray_on = self.toolpath.spray_on.copy()
            spray_on[starts] = False
            self.toolpath = dataclasses.replace(self.toolpath, spray_on=spray_on)
        self.cell = CellModel.from_scenario(scenario)
        if true_T_B_S is not None:  # the profilers as built, off the cell file's layout
            self.cell = dataclasses.replace(self.cell, T_B_S={k: np.asarray(v, dtype=float)
                                                              for k, v in true_T_B_S.items()})
        try:
            self.faults = FaultSchedule(scenario.faults, self.toolpath, self.cell)
        except ValueError as exc:  # a fault window the part cannot have: a scenario error
            raise ConfigError(f"scenario '{scenario.name}': {exc}") from None
        self.motion = execute_toolpath(self.toolpath, self.cell,
                                       rate_hz=self.cell.robot_state_hz,
                                       accel_mm_s2=self.cell.accel_mm_s2,
                                       dwell=self.dwell_for(self.toolpath))
        self.true_calibration = self.cell.calibration()
        self.calibration = perturbed_calibration(self.true_calibration,
                                                 scenario.calibration_error)
        t = self.motion.t_s
        self.end_s = float(t[-1]) if scenario.duration_s is None else min(
            float(t[-1]), float(scenario.duration_s))
        log.info("simulation: %d toolpath points, %d layers, %.1f s of process time",
                 len(self.toolpath), self.toolpath.n_layers, self.end_s)

    def dwell_for(self, toolpath) -> np.ndarray:
        """Stops [s] at each vertex: the corner-dwell faults, and ``layer_pause_s`` where each
        layer after the first has been approached, the powder off (the cell waiting for that
        layer's program)."""
        dwell = self.faults.corner_dwell_s(toolpath)
        if self.layer_pause_s > 0:
            dwell = dwell.copy()
            dwell[np.flatnonzero(np.diff(toolpath.layer)) + 1] += self.layer_pause_s
        return dwell

    def attachments(self) -> dict[str, bytes]:
        """Scenario (resolved TOML), toolpath (canonical CSV) and calibration (TOML)."""
        from dm2.core.calibration_io import calibration_to_toml
        from dm2.toolpath.formats import format_csv

        return {"scenario.toml": dump_toml(self.scenario.to_toml_dict()).encode(),
                "toolpath.csv": format_csv(self.toolpath).encode(),
                "calibration.toml": calibration_to_toml(self.calibration).encode()}

    def messages(self, truth_dir: str | Path | None = None, progress: Progress | None = None,
                 *, scan_thread: bool = True, worker_fan_share: float | None = None,
                 next_layer: NextLayer | None = None
                 ) -> Iterator[Profile | RobotState | LayerMark]:
        """The message stream in stamp order (deterministic for the scenario's seed).

        ``scan_thread`` deposits on a worker thread, which also casts a share of each profiler
        fan (balanced on the two threads' CPU seconds: :class:`twin.stream.threads.FanSplit`),
        while this one casts the rest and yields (the same messages either way, bit for bit;
        False keeps everything on the calling thread). ``worker_fan_share`` fixes the worker's
        share of each fan instead.

        ``next_layer`` closes the loop (:mod:`twin.stream.replan`): asked for each layer's
        toolpath as its first spraying move begins, once the stream before it has been taken;
        a new toolpath is executed from there with the robot's own dynamics (everything on
        the calling thread).
        """
        from twin.profiler.artefacts import schedule_artefacts
        from twin.profiler.occluders import nozzle_occluder
        from twin.profiler.sensor import VirtualProfiler
        from twin.profiler.trigger import trigger_schedule
        from twin.stream.truth_run import TruthWriter
        from twin.world.deposition import twin_spray_model
        from twin.world.heightfield import HeightField

        sc, cell, motion, faults = self.scenario, self.cell, self.motion, self.faults
        plate = sc.cell.plate_size_mm
        hf = HeightField(size_mm=(plate[0], plate[1]), cell_mm=HEIGHTFIELD_CELL_MM,
                         thickness_mm=plate[2])
        spray = twin_spray_model(sc)  # the twin's own physics ([twin_process])
        profilers = [VirtualProfiler(sid, cell.T_B_S[sid], sc.sensors, sc.noise, seed=sc.seed,
                                     T_B_N=cell.T_B_N) for sid in SENSOR_IDS]
        occluders = [nozzle_occluder(cell.T_B_N, sc.cell)]
        truth = TruthWriter(truth_dir, self) if truth_dir is not None else None
        robot_rng = np.random.default_rng([sc.seed, ROBOT_NOISE_SEED_OFFSET])
        robot_sigma = sc.noise.robot_repeatability_mm

        dt = 1.0 / cell.robot_state_hz
        scan_thread = scan_thread and next_layer is None

        def derive(motion):
            """The stream's per-sample and per-trigger arrays of ``motion`` (up to
            ``self.end_s``)."""
            t = motion.t_s
            n = int(np.searchsorted(t, self.end_s, side="right"))
            trig_s, trig_j, trig_c = trigger_schedule(float(t[n - 1]), sc.sensors)
            if n >= 2:
                trig_T_B_O = PoseInterpolator(t[:n], motion.T_B_O[:n])(trig_s)
            else:  # a single sample: every trigger (at most one, at t[0]) sees that pose
                trig_T_B_O = np.repeat(motion.T_B_O[:1], trig_s.size, axis=0)
            layers = motion.layer[:n]
            feed = faults.feed_factor(t[:n], layers)
            efficiency = faults.efficiency_factor(layers)
            standoff = faults.standoff_delta_mm(t[:n], layers)
            spraying = np.asarray(motion.spray_on[:n], dtype=bool)
            plan = spray.plan_samples(motion.position_O[:n], motion.axis_O[:n], dt,
                                      spray_on=spraying, feed_factor=feed,
                                      efficiency_factor=efficiency, standoff_delta_mm=standoff)
            # clock jitter and lost profiles (twin.profiler.artefacts): a profile is exposed
            # at its trigger, stamped off it; a lost one is never cast
            stamped_s, kept = schedule_artefacts(sc.noise, sc.seed, trig_s)
            if not kept.all():
                trig_s, trig_j, trig_c = trig_s[kept], trig_j[kept], trig_c[kept]
                stamped_s, trig_T_B_O = stamped_s[kept], trig_T_B_O[kept]
            # the feed over the plume particles' reference feed, at each trigger (0: off)
            trig_spray = (np.interp(trig_s, t[:n], spraying * feed)
                          * (sc.process.feed_g_min / sc.noise.plume_feed_ref_g_min)).tolist()
            chunks = list(chunk_runs(t[:n], layers, trig_s))
            trig_end = np.searchsorted(trig_s, [t[b] if b < n else np.inf for _, b in chunks],
                                       side="left").tolist()  # chunk c ends with these triggers
            return (t, n, trig_T_B_O, layers, t[:n].tolist(), spraying, plan,
                    stamped_s.tolist(), trig_j.tolist(), trig_c.tolist(), chunks, trig_end,
                    trig_spray)

        (t, n, trig_T_B_O, layers, stamps, spraying, plan, trig_stamps, trig_sensor,
         trig_counter, chunks, trig_end, trig_spray) = derive(motion)
        # The true field grows on a worker thread, a few chunks ahead: it deposits a chunk
        # (one GIL-free kernel call), casts its share of the chunk's profiler fans on the field
        # and hands over the cells the chunk changed, while this thread yields the chunk's
        # robot states, brings its mirror of the field to the chunk's end and casts the rest
        # of those fans there: same order, same bits as one thread, whatever the share.
        mirror = hf.copy() if scan_thread else hf  # (one thread: chunk by chunk, on hf)
        n_rays = profilers[0].dirs_S.shape[0]
        split = (FanSplit(n_rays, threaded=scan_thread) if worker_fan_share is None else
                 FanSplit(n_rays, scan_thread, worker_fan_share, step_rays=0))
        grown = [-1]  # the layer whose blobs the field holds
        blob_mm3 = [0.0]  # volume the injected bumps and dents added (the mass balance's)
        cpu = [0.0, 0.0]  # CPU seconds of the deposition calls, of all the worker's work

        def produce(c: int):
            """Chunk ``c`` on the true field: truth and blobs at a new layer, deposition, rays
            ``0:rays`` of its fans; returns (rays, traces, changed cells or None, CPU s), the
            traces measured into Profiles when ``rays`` is the whole fan."""
            c0 = time.thread_time()
            a, b = chunks[c]
            layer = int(layers[a])
            if layer != grown[0]:
                if grown[0] >= 0 and truth is not None:
                    truth.layer(hf, grown[0])
                v0 = float(hf.heights_mm.sum()) if truth is not None else 0.0
                if faults.apply_blobs(hf, layer) and truth is not None:  # as its layer starts
                    blob_mm3[0] += (float(hf.heights_mm.sum()) - v0) * hf.cell_mm ** 2
                grown[0] = layer
            if spraying[a:b].any():
                spray.deposit_plan(hf, plan, a, b)
            c1 = time.thread_time()
            rays, traces = split.rays, []
            k0 = trig_end[c - 1] if c else 0
            for q in range(k0, trig_end[c]) if rays else ():
                prof = profilers[trig_sensor[q]]
                out = prof.empty_trace()
                prof.trace_rays(hf, trig_T_B_O[q], occluders, out, 0, rays)
                # a whole fan is measured here too (the noise is drawn from the profile's own
                # (seed, sensor, counter) stream: the same bits on either thread)
                traces.append(out if rays < n_rays else
                              prof.measure(out, trig_stamps[q], trig_counter[q],
                                           trig_spray[q]))
            changes = (hf.take_changes() if mirror is not hf and trig_end[c] > k0
                       and rays < n_rays else None)
            c2 = time.thread_time()
            cpu[0] += c1 - c0
            cpu[1] += c2 - c0
            return rays, traces, changes, c2 - c0

        worker = (ChunkWorker(produce, len(chunks), threaded=scan_thread, name="twin-spray")
                  if next_layer is None else None)
        replan = Replanner(self, next_layer) if next_layer is not None else None
        k = 0  # next trigger
        layer_prev = -1
        c_main = time.thread_time()
        c = 0
        try:
            while c < len(chunks):
                a, b = chunks[c]
                layer = int(layers[a])
                if layer != layer_prev:
                    yield LayerMark(stamps[a], layer)
                    layer_prev = layer
                if replan is not None and spraying[a:b].any() and (
                        new := replan.at_layer(layer, motion, a)) is not None:
                    motion = new
                    (t, n, trig_T_B_O, layers, stamps, spraying, plan, trig_stamps,
                     trig_sensor, trig_counter, chunks, trig_end, trig_spray) = derive(motion)
                    c = replan.chunk_at(chunks, trig_end, a, k)
                # the executed motion holds finite float64 joints and rigid flange poses, so
                # the states skip re-validation; the noise draws match one (3,) draw per sample
                T_B_F = np.ascontiguousarray(motion.T_B_F[a:b], dtype=np.float64)
                if robot_sigma > 0:
                    T_B_F = T_B_F.copy()
                    T_B_F[:, :3, 3] += robot_rng.normal(0.0, robot_sigma, (b - a, 3))
                joints = np.ascontiguousarray(motion.joints_rad[a:b], dtype=np.float64)
                T_B_F.flags.writeable = False  # views of this chunk, so each state's rows are
                joints.flags.writeable = False  # read-only without a view per state
                for i in range(a, b):
                    yield RobotState.trusted(stamps[i], i, joints[i - a], T_B_F[i - a])
                    if progress is not None and (i % 250 == 0 or i == n - 1):
                        progress(stamps[i], self.end_s)
                rays, traces, changes, worker_s = (worker.result(c) if worker is not None
                                                   else produce(c))
                now = time.thread_time()
                split.balance(now - c_main, worker_s)
                c_main = now
                if changes is not None:
                    mirror.apply_changes(changes)
                for q in range(k, trig_end[c]):
                    prof = profilers[trig_sensor[q]]
                    if rays == 0:  # a whole fan in one call
                        yield prof.scan(mirror, trig_T_B_O[q], trig_stamps[q], trig_counter[q],
                                        occluders, trig_spray[q])
                        continue
                    out = traces[q - k]
                    if rays == n_rays:  # cast and measured on the worker
                        yield out
                        continue
                    prof.trace_rays(mirror, trig_T_B_O[q], occluders, out, rays, n_rays)
                    yield prof.measure(out, trig_stamps[q], trig_counter[q], trig_spray[q])
                k = trig_end[c]
                c += 1
        finally:
            if worker is not None:
                worker.close()
        if grown[0] >= 0 and truth is not None:  # (stopped early: as the worker left it)
            truth.layer(hf, grown[0])
        if truth is not None and n:
            truth.check_validity(hf, spray, float(plan.lam.sum()) * spray.v_packet_mm3,
                                 blob_mm3[0], int(layers[n - 1]))
            truth.finish(int(motion.segment[n - 1]))
        self.final_heightfield = hf
        self.spray_cpu_s, self.worker_cpu_s = cpu
        self.worker_fan_share = split.rays / max(split.n_rays, 1)


def iter_messages(scenario: TwinScenario, truth_dir: str | Path | None = None,
                  progress: Progress | None = None) -> Iterator[Profile | RobotState | LayerMark]:
    """The scenario's message stream, generated in process (same seed, same messages)."""
    yield from Simulation(scenario).messages(truth_dir, progress)


def simulate(scenario: TwinScenario, out_path: str | Path, truth_dir: str | Path | None = None,
             progress: Progress | None = None, *, simulation: Simulation | None = None,
             on_message: Callable[[object], None] | None = None) -> SimulationResult:
    """Run the twin and record it to MCAP at ``out_path`` (written as ``.part``, then renamed).

    ``simulation`` reuses an already prepared :class:`Simulation` of ``scenario``;
    ``on_message`` sees every message after it is written (e.g. a viewer).
    Raises ConfigError / ReachError before anything is written when the scenario is unusable.
    """
    from dm2.io.recording_writer import RecordingWriter

    sim = simulation if simulation is not None else Simulation(scenario)
    counts: Counter = Counter()
    with RecordingWriter(out_path, attachments=sim.attachments()) as writer:
        writer.write_static_tf(sim.calibration)
        for msg in sim.messages(truth_dir, progress):
            writer.write(msg)
            counts[type(msg).__name__] += 1
            if on_message is not None:
                on_message(msg)
    return SimulationResult(out_path=Path(out_path),
                            truth_dir=Path(truth_dir) if truth_dir is not None else None,
                            process_s=sim.end_s, counts=dict(counts),
                            n_layers=counts[LayerMark.__name__], calibration=sim.calibration)
