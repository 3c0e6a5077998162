"""The job registry is bounded: running jobs are capped, finished ones forgotten oldest
first, and a running job is never forgotten (issue 14: it kept the newest 1000 whatever
their state, and took any number of running jobs)."""

from __future__ import annotations

import pytest

from shared.jobs import Jobs, TooManyJobs, UnknownJob


def test_running_jobs_past_the_cap_are_refused_naming_it() -> None:
    jobs = Jobs(keep=10, max_running=2, setting="AESOP_TEST_MAX_JOBS")
    first, _ = jobs.create("add", "c", 1), jobs.create("add", "c", 1)
    with pytest.raises(TooManyJobs) as refused:
        jobs.create("add", "c", 1)
    assert refused.value.limit == 2 and "AESOP_TEST_MAX_JOBS" in str(refused.value)
    first.succeed({})
    jobs.create("add", "c", 1)  # a slot is free again


def test_finished_jobs_are_forgotten_oldest_first_and_running_ones_never() -> None:
    jobs = Jobs(keep=3, max_running=5)
    running = jobs.create("add", "c", 1)
    finished = []
    for _ in range(5):
        job = jobs.create("add", "c", 1)
        job.fail("x", "y")
        finished.append(job)
    jobs.create("add", "c", 1)  # the registry is trimmed when a job is made
    assert jobs.get(running.id) is running
    for old in finished[:2]:
        with pytest.raises(UnknownJob):
            jobs.get(old.id)
    assert [jobs.get(j.id) for j in finished[2:]] == finished[2:]
