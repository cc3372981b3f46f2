"""The twin's message stream from the plain per-sample loop: the executable specification.

:meth:`twin.stream.simulate.Simulation.messages` batches deposition between profiler triggers,
builds
robot states with the trusted constructor and scans with the numba profiler kernels. This
module keeps the straightforward loop it must equal bit for bit — one deposition call and one
validated ``RobotState`` per motion sample, the profilers' numpy path — so the tests
can prove the equality and the twin benchmark can measure the speed-up against it.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from dm2.core.frames import PoseInterpolator
from dm2.core.messages import SENSOR_IDS, LayerMark, Profile, RobotState


def per_sample_messages(sim, hf=None) -> Iterator[Profile | RobotState | LayerMark]:
    """The stream of ``sim`` (a :class:`twin.stream.simulate.Simulation`), one motion sample at a
    time.

    ``hf`` is the height field to grow (a new bare plate by default); pass one to inspect the
    reference's final surface.
    """
    from twin.profiler.artefacts import schedule_artefacts
    from twin.profiler.occluders import nozzle_occluder
    from twin.profiler.sensor import VirtualProfiler
    from twin.profiler.trigger import trigger_schedule
    from twin.stream.simulate import ROBOT_NOISE_SEED_OFFSET
    from twin.world.deposition import twin_spray_model
    from twin.world.heightfield import HEIGHTFIELD_CELL_MM, HeightField

    sc, cell, motion, faults = sim.scenario, sim.cell, sim.motion, sim.faults
    plate = sc.cell.plate_size_mm
    if hf is None:
        hf = HeightField((plate[0], plate[1]), HEIGHTFIELD_CELL_MM, plate[2])
    spray = twin_spray_model(sc)
    profs = [VirtualProfiler(s, cell.T_B_S[s], sc.sensors, sc.noise, seed=sc.seed,
                             T_B_N=cell.T_B_N) for s in SENSOR_IDS]
    occ = [nozzle_occluder(cell.T_B_N, sc.cell)]
    rng = np.random.default_rng([sc.seed, ROBOT_NOISE_SEED_OFFSET])
    sigma = sc.noise.robot_repeatability_mm
    t = motion.t_s
    n = int(np.searchsorted(t, sim.end_s, side="right"))
    trig_s, trig_j, trig_c = trigger_schedule(float(t[n - 1]), sc.sensors)
    stamped, kept = schedule_artefacts(sc.noise, sc.seed, trig_s)  # jitter, lost profiles
    trig_s, trig_j, trig_c, stamped = trig_s[kept], trig_j[kept], trig_c[kept], stamped[kept]
    poses = PoseInterpolator(t[:n], motion.T_B_O[:n])(trig_s)
    feed = faults.feed_factor(t[:n], motion.layer[:n])
    spray_now = np.interp(trig_s, t[:n], np.asarray(motion.spray_on[:n], bool) * feed) * (
        sc.process.feed_g_min / sc.noise.plume_feed_ref_g_min)
    eff = faults.efficiency_factor(motion.layer[:n])
    stand = faults.standoff_delta_mm(t[:n], motion.layer[:n])
    k, prev = 0, -1
    for i in range(n):
        layer = int(motion.layer[i])
        if layer != prev:
            faults.apply_blobs(hf, layer)
            yield LayerMark(float(t[i]), layer)
            prev = layer
        T_B_F = motion.T_B_F[i]
        if sigma > 0:
            T_B_F = T_B_F.copy()
            T_B_F[:3, 3] += rng.normal(0.0, sigma, 3)
        yield RobotState(float(t[i]), i, motion.joints_rad[i], T_B_F)
        if motion.spray_on[i]:
            spray.deposit(hf, motion.position_O[i], motion.axis_O[i], 1.0 / cell.robot_state_hz,
                          float(feed[i]), float(eff[i]), float(stand[i]))
        t_next = float(t[i + 1]) if i + 1 < n else np.inf
        while k < trig_s.size and trig_s[k] < t_next:
            p = profs[int(trig_j[k])]
            yield p.measure_numpy(p.trace_numpy(hf, poses[k], occ), float(stamped[k]),
                                  int(trig_c[k]), float(spray_now[k]))
            k += 1
