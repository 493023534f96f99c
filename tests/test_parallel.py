"""kpflow.eval.parallel: jobs in forked workers, in order, each worker set up once."""

import os

import pytest

from kpflow.eval.parallel import map_jobs

_STATE: dict = {}


def _setup(offset: int) -> None:
    _STATE.update(offset=offset, pid=os.getpid())


def _work(job: int) -> tuple[int, int]:
    return job + _STATE["offset"], _STATE["pid"]


@pytest.mark.parametrize("workers", [1, 2])
def test_map_jobs_keeps_the_order_and_runs_the_initializer_in_each_worker(workers):
    out = map_jobs(_work, list(range(20)), workers, _setup, (100,), progress=False)
    assert [value for value, _ in out] == list(range(100, 120))
    pids = {pid for _, pid in out}
    assert (pids == {os.getpid()}) if workers == 1 else (os.getpid() not in pids and len(pids) <= 2)
