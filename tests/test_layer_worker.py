"""The layer worker runs jobs in order, says whether one is still running (the session's
process fit waits for it without blocking the live loop), and re-raises a failure."""

import threading

import pytest

from dm2.pipeline.layer_worker import LayerWorker


def test_busy_until_every_submitted_job_has_run_and_again_after_a_join():
    done, gate = [], threading.Event()

    def job(k):
        gate.wait(5.0)
        done.append(k)

    w = LayerWorker(job)
    assert not w.busy
    for k in range(3):
        w.submit(k)
    assert w.busy and done == []
    gate.set()
    w.join()
    assert done == [0, 1, 2] and not w.busy
    gate.clear()
    w.submit(3)  # a new thread after the join
    assert w.busy
    gate.set()
    w.join()
    assert done == [0, 1, 2, 3] and not w.busy


def test_a_failed_job_stops_the_rest_and_is_raised_at_join():
    ran = []

    def job(k):
        ran.append(k)
        if k == 1:
            raise ValueError("bad layer")

    w = LayerWorker(job)
    for k in range(3):
        w.submit(k)
    with pytest.raises(RuntimeError, match="failed on its worker thread"):
        w.join()
    assert ran == [0, 1] and not w.busy
