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
    out = map_jobs(_work, list(range(20)), workers, initializer=_setup, initargs=(100,), progress=False)
    assert [value for value, _ in out] == list(range(100, 120))
    pids = {pid for _, pid in out}
    assert (pids == {os.getpid()}) if workers == 1 else (os.getpid() not in pids and len(pids) <= 2)


SCRIPT = """
import torch
from kpflow.eval.parallel import map_jobs

def work(n):
    x = torch.zeros(1_000_000).exp()  # large enough for torch's parallel_for
    return torch.get_num_threads(), int(x.sum())

torch.set_num_threads(2)
torch.zeros(1_000_000).exp()  # the parent's OpenMP pool now exists
print(map_jobs(work, list(range(4)), 2, progress=False))
"""


def test_forked_workers_run_torch_after_the_parent_did(tmp_path):
    """A parent that already ran a multi-threaded torch operation (OMP_NUM_THREADS unset) forks workers that still run
    torch, each on one thread: before they were given one thread, they waited on the parent's OpenMP pool for ever."""
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k != "OMP_NUM_THREADS"}
    done = subprocess.run([sys.executable, "-c", SCRIPT], env=env, capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.strip() == str([(1, 1_000_000)] * 4)
