"""Sharing the work with a worker thread (deposition and part of each profiler fan on the true
field, the rest of the fan over a mirror) changes no bit of the stream, whatever the share:
the same messages as with everything on the calling thread, and as the per-sample reference
loop, and the same final surface."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from dm2.core.config import parse_scenario
from tests.oracles.simulate_numpy import per_sample_messages
from twin.stream.simulate import Simulation


def _same(a, b) -> bool:
    if type(a) is not type(b):
        return False
    for name, va in vars(a).items():
        vb = getattr(b, name)
        if isinstance(va, np.ndarray):
            if not np.array_equal(va, vb, equal_nan=va.dtype.kind == "f"):
                return False
        elif va != vb:
            return False
    return True


def test_threaded_scans_equal_single_thread_and_reference():
    sim = Simulation(parse_scenario({
        "name": "scan_thread", "seed": 11, "duration_s": 1.2,
        "part": {"generator": "pad", "params": {"width_mm": 6.0, "depth_mm": 4.0,
                                                "height_mm": 1.6}},
        "toolpath": {"max_layers": 2, "layer_mm": 0.8},
        "noise": {"dropout_prob": 0.03, "outlier_prob": 0.02},
        "faults": [{"kind": "bump", "layers": [1, 1], "center_O_mm": [60.0, 60.0],
                    "height_mm": 0.8, "width_mm": 3.0}],
    }, "test"))
    threaded = list(sim.messages())
    h_threaded = sim.final_heightfield.heights_mm.copy()
    assert sim.worker_cpu_s >= sim.spray_cpu_s > 0
    for share in (0.0, 0.55, 1.0):  # the worker casts none, part or all of each fan
        fixed = list(sim.messages(worker_fan_share=share))
        assert sim.worker_fan_share == share
        assert all(_same(a, b) for a, b in zip(threaded, fixed, strict=True))
    inline = list(sim.messages(scan_thread=False))
    reference = list(per_sample_messages(sim))
    assert len(threaded) == len(inline) == len(reference)
    assert sum(type(m).__name__ == "Profile" for m in threaded) >= 30
    assert all(_same(a, b) for a, b in zip(threaded, inline, strict=True))
    assert all(_same(a, b) for a, b in zip(threaded, reference, strict=True))
    np.testing.assert_array_equal(h_threaded, sim.final_heightfield.heights_mm)
    assert h_threaded.max() > 0.5  # the pad grew (and the bump appeared)


def test_dirty_profilers_give_the_same_stream_on_every_path():
    # the realistic sensor preset (twin.profiler.artefacts): every artefact on, the same bits
    # threaded, inline and in the per-sample reference loop
    sim = Simulation(parse_scenario({
        "name": "dirty_scan_thread", "seed": 13, "duration_s": 1.5,
        "part": {"generator": "pad", "params": {"width_mm": 6.0, "depth_mm": 4.0,
                                                "height_mm": 1.6}},
        "toolpath": {"max_layers": 2, "layer_mm": 0.8},
        "noise": {"preset": "realistic", "lost_profile_prob": 0.1, "burst_prob": 0.5,
                  "plume_particle_prob": 0.5},
    }, "test"))
    threaded = list(sim.messages())
    inline = list(sim.messages(scan_thread=False))
    reference = list(per_sample_messages(sim))
    profiles = [m for m in threaded if type(m).__name__ == "Profile"]
    # lost profiles leave counter gaps; stamps are off their triggers by up to 1 ms
    assert len({(p.sensor_id, p.counter) for p in profiles}) == len(profiles) >= 30
    per_sensor = {}
    for p in profiles:
        per_sensor.setdefault(p.sensor_id, []).append(p.counter)
    assert any(np.any(np.diff(c) > 1) for c in per_sensor.values())
    assert len(threaded) == len(inline) == len(reference)
    assert all(_same(a, b) for a, b in zip(threaded, inline, strict=True))
    assert all(_same(a, b) for a, b in zip(threaded, reference, strict=True))


def test_a_stream_stopped_early_stops_its_worker():
    sim = Simulation(parse_scenario({
        "name": "stop_early", "seed": 2, "duration_s": 2.0,
        "part": {"generator": "pad", "params": {"width_mm": 6.0, "depth_mm": 4.0,
                                                "height_mm": 0.8}},
        "toolpath": {"max_layers": 1, "layer_mm": 0.8},
    }, "test"))
    stream = sim.messages()
    first = [next(stream) for _ in range(50)]  # the worker runs chunks ahead meanwhile
    assert len(first) == 50
    stream.close()
    assert not any(t.name == "twin-spray" for t in threading.enumerate())


def test_chunk_worker_hands_results_in_order_and_its_error_to_the_consumer():
    from twin.stream.threads import ChunkWorker

    def produce(c):
        if c == 5:
            raise RuntimeError("chunk 5 failed")
        return c * c

    for threaded in (True, False):
        worker = ChunkWorker(produce, 8, threaded=threaded, depth=2)
        try:
            assert [worker.result(c) for c in range(5)] == [0, 1, 4, 9, 16]
            with pytest.raises(ValueError, match="chunk 7 asked for, 5 is next"):
                worker.result(7)
            with pytest.raises(RuntimeError, match="chunk 5 failed"):
                worker.result(5)
        finally:
            worker.close()
