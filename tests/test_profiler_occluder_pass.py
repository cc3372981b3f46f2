"""The one-pass cylinder test used for camera rays gives the same verdicts as hit_t."""

import numpy as np

from dm2.core.frames import apply, from_euler_deg, invert
from twin.profiler.occluders import CylinderOccluder


def test_blocks_matches_hit_t_on_random_rays():
    rng = np.random.default_rng(5)
    T_B_C = from_euler_deg([5.0, -3.0, 40.0], [20.0, -35.0, 60.0])
    cyl = CylinderOccluder(T_B_C, radius_mm=8.0, length_mm=60.0)
    T_B_O = from_euler_deg([-20.0, 15.0, 0.0], [0.0, 10.0, -30.0])
    n = 4000
    starts_O = rng.uniform(-80.0, 80.0, (n, 3))
    # aim at points around the cylinder so that hits, misses and short reaches all occur
    aim_C = np.column_stack([rng.uniform(-16.0, 16.0, (n, 2)), rng.uniform(-10.0, 70.0, n)])
    aim_O = apply(invert(T_B_O) @ T_B_C, aim_C)
    dirs_O = aim_O - starts_O
    dirs_O /= np.linalg.norm(dirs_O, axis=1, keepdims=True)
    reach = rng.uniform(0.0, 150.0, n)
    starts_B = starts_O @ T_B_O[:3, :3].T + T_B_O[:3, 3]
    expected = cyl.hit_t(starts_B, dirs_O @ T_B_O[:3, :3].T) < reach
    got = np.zeros(n, dtype=bool)
    cyl.blocks(T_B_O, starts_O, dirs_O, reach, got)
    assert 200 < expected.sum() < n - 200  # both verdicts well represented
    np.testing.assert_array_equal(got, expected)
    already = np.ones(n, dtype=bool)
    cyl.blocks(T_B_O, starts_O, dirs_O, reach, already)
    assert already.all()  # a ray already blocked stays blocked
