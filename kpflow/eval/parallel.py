"""Running an experiment's independent jobs in forked worker processes, in order, with a progress bar.

Forked workers use one torch thread each. A process that has already run a parallel torch operation (a K-CFM or map
built from a checkpoint, with ``OMP_NUM_THREADS`` unset) holds an OpenMP thread pool that does not survive ``fork``:
a worker's first multi-threaded operation then waits for threads that do not exist, for ever. With one thread per
worker OpenMP never uses that pool (and the workers do not oversubscribe the cores either).
"""

from __future__ import annotations

import multiprocessing as mp
from typing import Callable, Iterator, Sequence

from tqdm import tqdm


def map_jobs(work: Callable, jobs: Sequence, workers: int, **options) -> list:
    """``[work(job) for job in jobs]``, computed by ``workers`` forked processes (each runs ``initializer(*initargs)``
    once first) or, for ``workers == 1``, in this process after ``initializer(*initargs)``; ``options``: those of
    :func:`iter_jobs`."""
    return list(iter_jobs(work, jobs, workers, **options))


def iter_jobs(
    work: Callable,
    jobs: Sequence,
    workers: int,
    initializer: Callable | None = None,
    initargs: tuple = (),
    desc: str = "jobs",
    unit: str = "job",
    progress: bool = True,
) -> Iterator:
    """:func:`map_jobs` as a generator: ``work(job)`` for each job in the order of ``jobs``, each yielded as soon as it
    and every job before it are done, so the caller can commit results while later jobs run. Closing the generator
    early (or an exception in the caller) terminates the workers; nothing is left running."""
    if workers > 1:
        pool = mp.get_context("fork").Pool(workers, initializer=_one_thread_then, initargs=(initializer, initargs))
        results = pool.imap(work, jobs)
    else:
        pool = None
        if initializer is not None:
            initializer(*initargs)
        results = map(work, jobs)
    finished = False
    try:
        yield from tqdm(results, total=len(jobs), desc=desc, unit=unit, disable=not progress)
        finished = True
    finally:
        if pool is not None:
            if finished:
                pool.close()
            else:
                pool.terminate()
            pool.join()


def _one_thread_then(initializer: Callable | None, initargs: tuple) -> None:
    """A forked worker's start: one torch thread (module docstring), then ``initializer(*initargs)``."""
    import torch

    torch.set_num_threads(1)
    if initializer is not None:
        initializer(*initargs)
