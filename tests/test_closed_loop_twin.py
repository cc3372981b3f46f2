"""The twin executes a corrected layer (``Simulation.messages(next_layer=...)``): the stream
up to the layer's first spraying move is the one it would have given, then the robot moves at
the new speeds with its own dynamics."""

from dataclasses import replace

import numpy as np

import twin  # noqa: F401  (registers the twin's scenario sections)
from dm2.core.config import load_scenario
from dm2.core.messages import LayerMark, RobotState
from twin.stream.simulate import Simulation

SCENARIO = "scenarios/suites/smoke/feed_step.toml"
FACTOR = 0.7


def _stream(sim, hook):
    msgs = list(sim.messages(next_layer=hook))
    states = [m for m in msgs if isinstance(m, RobotState)]
    marks = {m.layer: m.stamp_s for m in msgs if isinstance(m, LayerMark)}
    return states, marks


def test_a_slowed_layer_takes_longer_and_the_stream_before_it_is_unchanged():
    asked = []

    def slow_layer_1(layer):
        asked.append(layer)
        if layer != 1:
            return None
        tp = sim.toolpath
        speed = tp.speed_mm_s.copy()
        on = (tp.layer == 1) & tp.spray_on
        speed[on] *= FACTOR
        return replace(tp, speed_mm_s=speed)

    plain, plain_marks = _stream(Simulation(load_scenario(SCENARIO), layer_pause_s=1.5),
                                 lambda layer: None)
    sim = Simulation(load_scenario(SCENARIO), layer_pause_s=1.5)
    states, marks = _stream(sim, slow_layer_1)
    assert asked == [0, 1, 2]  # once per layer, as each begins to spray
    # layer 0 and layer 1's approach and pause: the same robot states, bit for bit
    t_pause_end = plain_marks[1] + 1.0
    same = [st for st in plain if st.stamp_s < t_pause_end]
    assert len(same) > 1000
    for a, b in zip(same, states, strict=False):
        assert a.stamp_s == b.stamp_s and np.array_equal(a.T_B_F, b.T_B_F)
    # layer 1 sprays at 0.7x: the robot's cruising speed there (the plate moves without
    # turning on a raster) is 0.7 of the programmed 30 mm/s; layer 0 as programmed
    def cruise(states, t0, t1):
        inside = [st for st in states if t0 <= st.stamp_s < t1]
        p = np.array([st.T_B_F[:3, 3] for st in inside])
        t = np.array([st.stamp_s for st in inside])
        v = np.linalg.norm(np.diff(p, axis=0), axis=1) / np.diff(t)
        return float(np.median(v[v > 5.0]))

    assert abs(cruise(plain, plain_marks[1] + 1.5, plain_marks[2]) - 30.0) < 0.5
    assert abs(cruise(states, marks[1] + 1.5, marks[2]) - 30.0 * FACTOR) < 0.5
    assert abs(cruise(states, marks[0], marks[1]) - 30.0) < 0.5
    assert marks[2] - marks[1] > plain_marks[2] - plain_marks[1] + 1.0  # the slower layer
