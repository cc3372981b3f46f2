"""dm2 sweep on a Dask LocalCluster of worker processes: same seeds, same results."""

import json

import pytest

from dm2.bench.sweep import run_sweep, summarize_sweep, sweep_cases


@pytest.fixture(scope="module")
def client():
    from distributed import Client, LocalCluster

    cluster = LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                           dashboard_address=None)
    c = Client(cluster)
    yield c
    c.close()
    cluster.close()


def _base():
    from dm2.bench.suites import apply_overrides
    from dm2.core.config import load_scenario
    from scenarios import scenario_dir

    sc = load_scenario(scenario_dir() / "suites" / "smoke" / "bump.toml").to_toml_dict()
    # two layers; the blob appears as layer 0 starts, so layer 0's scans see it
    return apply_overrides(sc, ["toolpath.max_layers=2", "faults.0.layers=[0, 0]"])


@pytest.fixture(scope="module")
def sweep(client):
    from dm2.cli.bench_runner import sweep_case

    cases = sweep_cases(_base(), [0.3, 1.5], [3, 4])
    first = run_sweep(cases, sweep_case, client=client)
    second = run_sweep(cases[::-1], sweep_case, client=client)[::-1]
    return first, second


def test_tiny_sweep_is_reproducible_on_a_local_cluster(sweep):
    first, second = sweep
    assert json.dumps(first, sort_keys=True) == json.dumps(second, sort_keys=True)
    summ = summarize_sweep(first)
    big = summ["by_size"][1]
    assert big["size"] == 1.5 and big["probability"] == 1.0
    assert summ["smallest_reliable_size"] in (0.3, 1.5)
    for r in first:
        if r["size"] == 1.5:
            assert r["onset_delay_layers"] == 0 and r["peak_height_mm"] > 1.0
    # the seed changes the stream: different seeds, different reconstructions
    assert first[2]["reconstruction_rms_mm"] != first[3]["reconstruction_rms_mm"]


def test_tiny_sweep_has_no_false_track(sweep):
    first, _ = sweep
    assert all(r["false_positive_tracks"] == 0 for r in first)


def test_cluster_chatter_is_held_back_for_the_block_then_restored(caplog):
    """The local cluster's INFO life cycle (and the tracebacks its shutdown logs at INFO) stays
    out of the console; warnings still show; the logger's own level comes back after."""
    import logging

    from dm2.bench.sweep import _logger_level

    logger = logging.getLogger("distributed.test_child")
    parent = logging.getLogger("distributed")
    parent.setLevel(logging.NOTSET)
    with caplog.at_level(logging.INFO), _logger_level("distributed", logging.WARNING):
        logger.info("Batched Comm Closed")
        logger.warning("worker lost")
    assert [r.getMessage() for r in caplog.records] == ["worker lost"]
    assert parent.level == logging.NOTSET
