"""``Pipeline``: ``run(source)`` is the session fed message by message, live feeding
(``feed``/``catch_up``/``finish``) gives the same layers and tracks, and ``write_outputs`` /
``write_layer_surface`` write what the pipeline holds."""

import csv
import json

import numpy as np
import pytest
import trimesh

from dm2.core.config import load_scenario
from dm2.pipeline.pipeline import STAGES, Pipeline
from dm2.pipeline.session import MonitoringSession
from scenarios import resolve_scenario


@pytest.fixture(scope="module")
def pad_stream():
    from twin.stream.simulate import Simulation

    sc = load_scenario(resolve_scenario("pad")).model_copy(update={"duration_s": 14.0})
    sim = Simulation(sc)
    return sc, sim, list(sim.messages())


def _pipeline(pad_stream, live: bool = False) -> Pipeline:
    sc, sim, _ = pad_stream
    p = Pipeline(sim.calibration, sc.monitor, sc.process, sc.cell.plate_size_mm,
                 toolpath=sim.toolpath, live=live)
    p.fusion.max_delay_s = np.inf  # batches by count only: no wall-clock dependence
    return p


@pytest.fixture(scope="module")
def ran(pad_stream):
    p = _pipeline(pad_stream)
    p.run(iter(pad_stream[2]))  # any iterable: a generator here
    return p


def _same_layers_and_tracks(a, b) -> None:
    assert len(a.fusion.layer_done) >= 2
    for x, y in zip(a.fusion.layer_done, b.fusion.layer_done, strict=True):
        assert x.layer == y.layer and x.stamp_s == y.stamp_s
        assert np.array_equal(x.surface.vertices_O, y.surface.vertices_O)
        assert np.array_equal(x.surface.faces, y.surface.faces)
    assert [r.layer for r in a.results] == [r.layer for r in b.results]
    for ra, rb in zip(a.results, b.results, strict=True):
        assert np.array_equal(ra.deviation.signed_distance_mm, rb.deviation.signed_distance_mm)
        assert [(g.kind, g.area_mm2) for g in ra.regions] == \
            [(g.kind, g.area_mm2) for g in rb.regions]
    assert [(t.id, t.kind) for t in a.tracks] == [(t.id, t.kind) for t in b.tracks]


def test_run_is_the_session_fed_message_by_message(pad_stream, ran):
    sc, sim, msgs = pad_stream
    s = MonitoringSession(sim.calibration, sc.monitor, sc.process, sc.cell.plate_size_mm,
                          toolpath=sim.toolpath)
    s.fusion.max_delay_s = np.inf
    for m in msgs:
        s.feed(m)
    s.finish()
    _same_layers_and_tracks(s, ran)
    assert ran.messages == len(msgs)
    assert ran.dropped == s.dropped
    assert list(ran.stages()) == list(STAGES)
    assert ran.stages()["fuse"] is ran.fusion.tsdf


def test_live_feeding_gives_the_same_layers_and_tracks(pad_stream, ran):
    p = _pipeline(pad_stream, live=True)
    for i, m in enumerate(pad_stream[2]):
        p.feed(m)
        if i % 7 == 0:
            p.catch_up()
    p.finish()
    _same_layers_and_tracks(ran, p)


def test_write_outputs_and_layer_surface(ran, tmp_path):
    report = ran.write_outputs(tmp_path / "lite", full=False, config_toml="x = 1\n",
                               meta={"case": "pad"}, command="dm2 bench")
    on_disk = json.loads((tmp_path / "lite" / "report.json").read_text())
    assert on_disk["tracks"] == report["tracks"]
    assert [t["id"] for t in on_disk["tracks"]] == [t.id for t in ran.tracks]
    assert [r["layer"] for r in on_disk["layers"]] == [r.layer for r in ran.results]
    assert on_disk["realtime"]["frame_sets"] == ran.sections()["realtime"]["frame_sets"]
    with open(tmp_path / "lite" / "tracks.csv") as f:
        rows = list(csv.DictReader(f))  # one row per track and layer seen
    assert sorted({int(r["track_id"]) for r in rows}) == sorted(t.id for t in ran.tracks)
    assert len(rows) == sum(len(t.history) for t in ran.tracks)
    assert (tmp_path / "lite" / "config.toml").read_text() == "x = 1\n"

    entry = ran.write_layer_surface(tmp_path, index=0)
    first = ran.fusion.layer_done[0]
    assert entry["layer"] == first.layer and entry["file"] == f"layer_{first.layer:04d}.ply"
    mesh = trimesh.load(tmp_path / entry["file"], force="mesh", process=False)
    assert np.allclose(mesh.vertices, first.surface.vertices_O, atol=1e-5)
    assert np.array_equal(mesh.faces, first.surface.faces)


def test_a_replay_does_not_depend_on_how_fast_it_is_read(pad_stream):
    """A replay fuses full batches only: pauses while reading the stream (a slow disk, a
    garbage collection, a first run compiling its kernels) move no batch of the fusion and no
    real-time comparison, so the layers, tracks and real-time comparisons are the same."""
    import time

    sc, sim, msgs = pad_stream
    runs = []
    for pause_every in (0, 97):
        p = Pipeline(sim.calibration, sc.monitor, sc.process, sc.cell.plate_size_mm,
                     toolpath=sim.toolpath)
        stamps = []
        rt = p.session.realtime
        compare = rt.update_from_tsdf

        def spy(tsdf, spot_O, stamp, reference, _compare=compare, _stamps=stamps):
            _stamps.append(stamp)
            return _compare(tsdf, spot_O, stamp, reference)

        rt.update_from_tsdf = spy

        def source(every=pause_every):
            for i, m in enumerate(msgs):
                if every and i % every == every - 1:
                    time.sleep(0.03)  # longer than a live stream's batch delay
                yield m

        p.run(source())
        runs.append((p, stamps))
    (a, stamps_a), (b, stamps_b) = runs
    assert len(stamps_a) > 50 and stamps_a == stamps_b
    _same_layers_and_tracks(a, b)
