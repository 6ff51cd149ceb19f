"""fullperc_common.background.Job: one call at a time, on the worker or at once; its result given once, on the
caller's thread, its exception too."""

from __future__ import annotations

import threading

import pytest

from fullperc_common.background import Job
from fullperc_common.testing import wait_for


def _wait(job: Job) -> tuple[bool, object]:
    wait_for(lambda: job.ready, 60.0, 0.005, what="the worker's call")   # a liveness bound, not a time limit
    return job.poll()


def test_at_once_the_result_is_ready_at_the_first_poll_and_given_once():
    job = Job(lambda a, b: a + b, background=False)
    assert job.poll() == (False, None) and not job.running
    assert job.start(2, 3) and job.running
    assert not job.start(1, 1)                 # the result not yet taken: nothing started
    assert job.poll() == (True, 5) and job.poll() == (False, None) and not job.running


def test_on_the_worker_the_call_runs_on_another_thread_and_start_does_not_wait_for_it():
    gate, caller = threading.Event(), threading.get_ident()
    job = Job(lambda: (gate.wait(60.0), threading.get_ident())[1], background=True)
    assert job.start() and job.running
    assert job.poll() == (False, None)         # held by the gate: start returned before the call finished
    assert not job.start()
    gate.set()
    done, ident = _wait(job)
    assert done and ident != caller and not job.running and job.poll() == (False, None)


def test_an_exception_of_the_call_is_raised_at_the_poll_that_takes_it():
    def boom():
        raise ValueError("bad window")

    for background in (False, True):
        job = Job(boom, background)
        job.start()
        with pytest.raises(ValueError, match="bad window"):
            _wait(job)
        assert not job.running
