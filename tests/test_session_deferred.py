"""Deferred feeding (live mode) gives the same reference, surfaces, layer results and tracks
as immediate feeding, however the catch-up work is sliced and interrupted."""

import threading

import numpy as np
import pytest

import dm2.fusion.surface as surface_mod
import dm2.pipeline.session as session_mod
from dm2.core.config import load_scenario
from dm2.pipeline.session import MonitoringSession
from scenarios import resolve_scenario


@pytest.fixture(scope="module")
def pad_stream():
    from twin.stream.simulate import Simulation

    sc = load_scenario(resolve_scenario("pad")).model_copy(update={"duration_s": 14.0})
    sim = Simulation(sc)
    return sc, sim, list(sim.messages())


def _run(pad_stream, defer: bool, catch_up_every: int = 5, yield_every: int = 3):
    sc, sim, msgs = pad_stream
    s = MonitoringSession(sim.calibration, sc.monitor, sc.process, sc.cell.plate_size_mm,
                          toolpath=sim.toolpath, analysis_thread=defer)
    s.fusion.max_delay_s = np.inf  # batches by count only: no wall-clock dependence
    asked = [0]

    def should_yield() -> bool:  # an inbox that fills up every few slices
        asked[0] += 1
        return asked[0] % yield_every == 0

    for i, m in enumerate(msgs):
        s.feed(m, defer=defer)
        if defer and i % catch_up_every == 0:
            s.catch_up(should_yield)
    s.finish()
    return s


@pytest.fixture(scope="module")
def immediate(pad_stream):
    return _run(pad_stream, defer=False)


@pytest.mark.parametrize("every", [1, 40])
def test_deferred_matches_immediate_bit_for_bit(pad_stream, immediate, every, monkeypatch):
    monkeypatch.setattr(session_mod, "PREMESH_EVERY_S", 0.0)  # pre-mesh at every catch-up
    meshed_on, gathering = [], set()  # threads inside a gather right now
    mesh_volume, gather = surface_mod.mesh_volume, surface_mod.SurfaceExtractor.gather

    def noted_mesh(*args):
        me = threading.current_thread()
        meshed_on.append((me.name, me.ident in gathering))
        return mesh_volume(*args)

    def noted_gather(self):
        gathering.add(threading.get_ident())
        try:
            return gather(self)
        finally:
            gathering.discard(threading.get_ident())

    monkeypatch.setattr(surface_mod, "mesh_volume", noted_mesh)
    monkeypatch.setattr(surface_mod.SurfaceExtractor, "gather", noted_gather)
    a, b = immediate, _run(pad_stream, defer=True, catch_up_every=every)
    # layer ends only copied chunk boxes on the fusion thread; the worker meshed them
    assert not any(in_gather for _, in_gather in meshed_on)
    assert sum(name == "layer-analysis" for name, _ in meshed_on) > 0
    assert len(a.fusion.layer_done) >= 2
    assert np.array_equal(a.reference.heights_mm, b.reference.heights_mm)
    for x, y in zip(a.fusion.layer_done, b.fusion.layer_done, strict=True):
        assert x.layer == y.layer and x.stamp_s == y.stamp_s
        assert np.array_equal(x.surface.vertices_O, y.surface.vertices_O)
        assert np.array_equal(x.surface.faces, y.surface.faces)
        assert np.array_equal(x.surface.weight, y.surface.weight)
    assert [r.layer for r in a.results] == [r.layer for r in b.results]
    for ra, rb in zip(a.results, b.results, strict=True):
        assert [(g.kind, g.area_mm2) for g in ra.regions] == \
            [(g.kind, g.area_mm2) for g in rb.regions]
    assert [(t.id, t.kind) for t in a.tracks] == [(t.id, t.kind) for t in b.tracks]
    # the real-time comparison ran at the newest profile whenever the loop caught up
    n_a, n_b = (s.realtime_summary()["frame_sets"] for s in (a, b))
    assert n_b <= n_a and n_b > (n_a // 20 if every > 1 else n_a // 2)


def test_catch_up_gives_way_and_resumes(pad_stream):
    sc, sim, msgs = pad_stream
    s = MonitoringSession(sim.calibration, sc.monitor, sc.process, sc.cell.plate_size_mm,
                          toolpath=sim.toolpath)
    for m in msgs[:400]:
        s.feed(m, defer=True)
    assert s.behind and s.realtime_summary()["frame_sets"] == 0
    assert s.catch_up(lambda: True) is False  # a message waits: one slice at most, then back
    assert s.behind
    while not s.catch_up():
        pass
    assert not s.behind and s.realtime_summary()["frame_sets"] == 1
    assert s.reference.stamp_s > 0.0
