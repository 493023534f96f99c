"""Running an experiment's independent jobs in forked worker processes, in order, with a progress bar."""

from __future__ import annotations

import multiprocessing as mp
from typing import Callable, Sequence

from tqdm import tqdm


def map_jobs(
    work: Callable,
    jobs: Sequence,
    workers: int,
    initializer: Callable | None = None,
    initargs: tuple = (),
    desc: str = "jobs",
    unit: str = "job",
    progress: bool = True,
) -> list:
    """``[work(job) for job in jobs]``, computed by ``workers`` forked processes (each runs ``initializer(*initargs)``
    once first) or, for ``workers == 1``, in this process after ``initializer(*initargs)``."""
    if workers > 1:
        pool = mp.get_context("fork").Pool(workers, initializer=initializer, initargs=initargs)
        results = pool.imap(work, jobs)
    else:
        pool = None
        if initializer is not None:
            initializer(*initargs)
        results = map(work, jobs)
    try:
        return list(tqdm(results, total=len(jobs), desc=desc, unit=unit, disable=not progress))
    finally:
        if pool is not None:
            pool.close()
            pool.join()
