"""The twin's orchestrator: stream order and rates, determinism, physics seen by the profilers,
robot noise only on the reported pose, and a recording that replays the in-process stream."""

from __future__ import annotations

import tomllib

import numpy as np
import pytest

from dm2.core.config import parse_scenario
from dm2.core.frames import apply, invert
from dm2.core.messages import LayerMark, Profile, RobotState
from dm2.io.recording import read_recording
from tests.oracles.messages import assert_same_message

DURATION_S = 1.2


def _scenario(**over):
    data = {"name": "sim_test", "seed": 5, "duration_s": DURATION_S,
            "part": {"generator": "seven_sided"},
            "toolpath": {"max_layers": 1},
            # a slim nozzle body keeps every camera's view of the spot clear in this test
            "cell": {"nozzle_body_diameter_mm": 10.0},
            "calibration_error": {"translation_mm": [0.5, 0.0, 0.0], "sensors": ["S2"]}}
    data.update(over)
    return parse_scenario(data, "test")


@pytest.fixture(scope="module")
def sim_and_messages():
    from twin.stream.simulate import Simulation

    sim = Simulation(_scenario())
    return sim, list(sim.messages())


def test_stream_order_rates_and_counters(sim_and_messages):
    sim, msgs = sim_and_messages
    stamps = np.array([m.stamp_s for m in msgs])
    assert np.all(np.diff(stamps) >= 0)
    assert isinstance(msgs[0], LayerMark) and msgs[0].layer == 0 and msgs[0].stamp_s == 0.0
    states = [m for m in msgs if isinstance(m, RobotState)]
    hz = sim.cell.robot_state_hz
    assert len(states) == int(DURATION_S * hz) + 1
    assert [s.seq for s in states] == list(range(len(states)))
    np.testing.assert_allclose(np.diff([s.stamp_s for s in states]), 1.0 / hz, atol=1e-9)
    profiles = [m for m in msgs if isinstance(m, Profile)]
    assert stamps[-1] <= DURATION_S + 1e-9
    for j, sid in enumerate(("S1", "S2", "S3")):
        mine = [p for p in profiles if p.sensor_id == sid]
        k = np.arange(len(mine))
        np.testing.assert_allclose([p.stamp_s for p in mine], k / 10.0 + 0.02 * j, atol=1e-9)
        assert [p.counter for p in mine] == list(k)
        assert all(p.n_points == 640 for p in mine)
    # the true robot state: flange pose and joints agree with the executed motion
    np.testing.assert_array_equal(states[7].T_B_F, sim.motion.T_B_F[7])


def test_same_seed_same_stream(sim_and_messages):
    sim, msgs = sim_and_messages
    again = list(sim.messages())
    assert len(again) == len(msgs)
    for a, b in zip(msgs, again, strict=True):
        assert_same_message(a, b)


def test_profiles_see_the_plate_where_the_robot_holds_it(sim_and_messages):
    """Map each profile into O with the true calibration and the plate pose at its stamp: the
    points lie on the true surface (bare plate at z_O = 0 away from the fresh deposit)."""
    sim, msgs = sim_and_messages
    hf = sim.final_heightfield
    cal = sim.true_calibration
    from dm2.core.frames import PoseInterpolator

    interp = PoseInterpolator(sim.motion.t_s[:400], sim.motion.T_B_O[:400])
    residuals, n_valid = [], 0
    for p in (m for m in msgs if isinstance(m, Profile)):
        pts_S = np.column_stack([p.xz_S[p.valid, 0], np.zeros(p.valid.sum()),
                                 p.xz_S[p.valid, 1]])
        T_O_S = invert(interp([p.stamp_s])[0]) @ cal.T_B_S[p.sensor_id]
        pts_O = apply(T_O_S, pts_S)
        n_valid += len(pts_O)
        inside = ((pts_O[:, 0] > 1) & (pts_O[:, 0] < 119) & (pts_O[:, 1] > 1)
                  & (pts_O[:, 1] < 119))
        residuals.append(pts_O[inside, 2] - hf.height_at(pts_O[inside, :2]))
    r = np.concatenate(residuals)
    assert n_valid > 0.5 * 640 * sum(isinstance(m, Profile) for m in msgs)
    # range noise 0.05 mm; deposit still growing after a scan makes the truth a bit higher
    assert abs(np.median(r)) < 0.05
    assert np.mean(np.abs(r) < 0.3) > 0.95


def test_robot_noise_moves_only_the_reported_pose():
    from twin.stream.simulate import Simulation

    sigma = 0.2
    sim = Simulation(_scenario(duration_s=0.4, noise={"robot_repeatability_mm": sigma}))
    states = [m for m in sim.messages() if isinstance(m, RobotState)]
    d = np.array([s.T_B_F[:3, 3] - sim.motion.T_B_F[s.seq][:3, 3] for s in states])
    assert 0.7 * sigma < d.std() < 1.3 * sigma
    assert abs(d.mean()) < 0.1
    for s in states:
        np.testing.assert_array_equal(s.joints_rad, sim.motion.joints_rad[s.seq])
        np.testing.assert_array_equal(s.T_B_F[:3, :3], sim.motion.T_B_F[s.seq][:3, :3])


def test_recording_replays_the_in_process_stream(sim_and_messages, tmp_path):
    from twin.stream.simulate import simulate

    sim, msgs = sim_and_messages
    out = tmp_path / "run.mcap"
    result = simulate(sim.scenario, out, simulation=sim)
    assert result.counts["Profile"] == sum(isinstance(m, Profile) for m in msgs)
    rec = read_recording(out)
    back = list(rec.messages())
    assert len(back) == len(msgs)
    key = lambda m: (type(m).__name__, getattr(m, "sensor_id", ""), round(m.stamp_s * 1e9))  # noqa: E731
    orig = {key(m): m for m in msgs}
    for b in back:
        m = orig[key(b)]
        if isinstance(m, Profile):
            assert b.counter == m.counter and np.array_equal(b.valid, m.valid)
            np.testing.assert_allclose(b.xz_S[b.valid], m.xz_S[m.valid], rtol=1.2e-7)
        elif isinstance(m, RobotState):
            np.testing.assert_allclose(b.T_B_F, m.T_B_F, atol=1e-9)
    # attachments make it self-contained: scenario, toolpath, calibration handed to the pipeline
    sc = parse_scenario(tomllib.loads(rec.scenario_toml), "attachment")
    assert sc == sim.scenario
    tp = rec.toolpath
    np.testing.assert_allclose(tp.position_O, sim.toolpath.position_O, atol=1e-6)
    assert np.array_equal(tp.layer, sim.toolpath.layer)
    cal = rec.calibration
    shift = (invert(sim.true_calibration.T_B_S["S2"]) @ cal.T_B_S["S2"])[:3, 3]
    np.testing.assert_allclose(shift, [0.5, 0.0, 0.0], atol=1e-9)  # the perturbed one
    np.testing.assert_allclose(cal.T_B_S["S1"], sim.true_calibration.T_B_S["S1"], atol=1e-9)
