"""Cascaded trigger schedule of the three profilers and 24-bit counters."""

from __future__ import annotations

import numpy as np
import pytest

from dm2.core.config import SensorConfig
from dm2.core.messages import COUNTER_MODULO
from twin.profiler.trigger import trigger_schedule


def test_cascade_stamps_are_exact():
    sensors = SensorConfig()
    t0 = 12.3
    stamps, j, counter = trigger_schedule(t0 + 5.0, sensors, t0_s=t0)
    k = counter  # start counter 0: the counter is the trigger number
    np.testing.assert_allclose(stamps, t0 + k / 10.0 + j * 0.020, rtol=0, atol=1e-12)
    assert np.all(np.diff(stamps) > 0)
    assert stamps[0] == t0 and stamps.max() <= t0 + 5.0
    # 51 triggers in [t0, t0 + 5]; the last one only fires S1 before t_end
    assert np.array_equal(np.bincount(j), [51, 50, 50])
    np.testing.assert_array_equal(j[:6], [0, 1, 2, 0, 1, 2])
    for s in range(3):
        np.testing.assert_array_equal(counter[j == s], np.arange(np.sum(j == s)))


def test_counters_wrap_at_24_bits_from_a_start_counter():
    sensors = SensorConfig()
    start = [COUNTER_MODULO - 2, 7, COUNTER_MODULO - 1]
    stamps, j, counter = trigger_schedule(0.35, sensors, start_counter=start)
    np.testing.assert_array_equal(counter[j == 0], [COUNTER_MODULO - 2, COUNTER_MODULO - 1, 0, 1])
    np.testing.assert_array_equal(counter[j == 1], [7, 8, 9, 10])
    np.testing.assert_array_equal(counter[j == 2], [COUNTER_MODULO - 1, 0, 1, 2])
    assert counter.max() < COUNTER_MODULO


def test_slow_cascade_still_orders_by_stamp_and_rejects_bad_start():
    sensors = SensorConfig(rate_hz=20.0, cascade_s=0.03)  # S3 fires after the next S1
    stamps, j, _ = trigger_schedule(1.0, sensors)
    assert np.all(np.diff(stamps) >= 0)
    np.testing.assert_array_equal(j[:4], [0, 1, 0, 2])
    assert trigger_schedule(-1.0, sensors)[0].size == 0
    with pytest.raises(ValueError, match="start_counter"):
        trigger_schedule(1.0, sensors, start_counter=-1)
