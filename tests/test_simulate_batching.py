"""The batched simulation loop gives, bit for bit, the stream of the plain per-sample loop:
one deposition call per motion sample, validated robot states, the numpy path of the profilers
(trace and noise), robot noise drawn three values at a time; and the trusted state constructor
equals the validating one."""

from __future__ import annotations

import numpy as np
import pytest

from dm2.core.config import parse_scenario
from dm2.core.messages import LayerMark, Profile, RobotState
from tests.oracles.messages import assert_same_message
from tests.oracles.simulate_numpy import per_sample_messages
from twin.stream.simulate import Simulation
from twin.stream.threads import chunk_runs
from twin.world.heightfield import HEIGHTFIELD_CELL_MM


def _scenario():
    # a 6 x 4 mm pad: layer 1 starts at 0.53 s, so the run crosses a layer change
    return parse_scenario({
        "name": "batching", "seed": 3, "duration_s": 1.5,
        "part": {"generator": "pad", "params": {"width_mm": 6.0, "depth_mm": 4.0,
                                                "height_mm": 1.6}},
        "toolpath": {"max_layers": 2, "layer_mm": 0.8},
        "noise": {"robot_repeatability_mm": 0.05, "speckle_sigma_mm": 0.02,
                  "dropout_prob": 0.03, "outlier_prob": 0.02},
        "faults": [{"kind": "feed_step", "factor": 1.7, "time_s": [0.3, 0.9]},
                   {"kind": "standoff_change", "delta_mm": 2.0, "time_s": [0.2, 1.1]}],
    }, "test")


def _per_sample_stream(sim: Simulation):
    """The plain per-sample loop (the reference) and the height field it grew."""
    from twin.world.heightfield import HeightField

    plate = sim.scenario.cell.plate_size_mm
    hf = HeightField((plate[0], plate[1]), HEIGHTFIELD_CELL_MM, plate[2])
    return list(per_sample_messages(sim, hf)), hf


@pytest.fixture(scope="module")
def sim():
    return Simulation(_scenario())


def test_batched_stream_equals_per_sample_loop_bit_for_bit(sim):
    batched = list(sim.messages())
    reference, hf_ref = _per_sample_stream(sim)
    assert [type(m).__name__ for m in batched] == [type(m).__name__ for m in reference]
    kinds = {type(m) for m in batched}
    assert kinds == {LayerMark, RobotState, Profile}
    assert [m.layer for m in batched if isinstance(m, LayerMark)] == [0, 1]
    for a, b in zip(batched, reference, strict=True):
        assert_same_message(a, b)
    np.testing.assert_array_equal(sim.final_heightfield.heights_mm, hf_ref.heights_mm)
    assert float(hf_ref.heights_mm.max()) > 0.3  # something was deposited and scanned
    assert sum(int(m.valid.sum()) for m in batched if isinstance(m, Profile)) > 1000


def test_trusted_robot_state_equals_validated(sim):
    m = sim.motion
    for i in (0, 17, len(m) - 1):
        a = RobotState(float(m.t_s[i]), i, m.joints_rad[i], m.T_B_F[i])
        b = RobotState.trusted(np.float64(m.t_s[i]), np.int64(i), m.joints_rad[i], m.T_B_F[i])
        assert_same_message(a, b)
    joints, T = m.joints_rad[:3].copy(), m.T_B_F[:3].copy()
    joints.flags.writeable = T.flags.writeable = False  # rows taken as they are
    b = RobotState.trusted(1.5, 2, joints[2], T[2])
    assert_same_message(RobotState(1.5, 2, joints[2], T[2]), b)
    assert b.T_B_F.base is T


def test_trusted_profile_equals_validated():
    rng = np.random.default_rng(3)
    xz = rng.normal(size=(640, 2))
    valid = rng.random(640) > 0.2
    xz[~valid] = np.nan
    intensity = rng.random(640).astype(np.float32)
    a = Profile("S2", 0.52, (1 << 24) - 1, xz.copy(), valid.copy(), intensity.copy())
    b = Profile.trusted("S2", np.float64(0.52), np.int64((1 << 24) - 1), xz, valid, intensity)
    assert np.isnan(b.xz_S[~valid]).all()
    assert_same_message(a, b)
    assert b.xz_S is xz  # no copy: the producer's array, now read-only


def test_chunks_cut_at_triggers_and_layer_changes():
    t = np.arange(10) * 0.1
    layer = np.array([0, 0, 0, 0, 1, 1, 1, 1, 1, 1])
    trig = np.array([-0.05, 0.0, 0.25, 0.25, 0.65, 0.9])
    runs = list(chunk_runs(t, layer, trig))
    # triggers answered after samples 0, 0, 2, 2, 6, 9; layer 1 starts at sample 4
    assert runs == [(0, 1), (1, 3), (3, 4), (4, 7), (7, 10)]
    assert list(chunk_runs(t[:1], layer[:1], np.array([0.0]))) == [(0, 1)]
