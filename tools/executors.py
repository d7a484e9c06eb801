"""One way to run independent jobs, for `collect` (episodes) and `evaluate`
(trials): in this process, in spawned worker processes, or on Ray actors.

Each worker calls `init(*init_args)` once, then `run(job)` per job; both
are module-level functions (pickled by reference). Jobs may be an endless
iterator; the caller stops by leaving its loop (closing the generator
terminates the worker processes, or waits for the Ray jobs in flight).
"""

import multiprocessing as mp
from collections.abc import Callable, Iterable, Iterator

from fabric_imitation.learning.errors import InputError

EXECUTORS = ("local", "ray")


def StartRay(workers: int):
    """The `ray` module, started locally with `workers` CPUs unless a Ray is
    already connected; a one-line InputError when Ray is not installed."""
    try:
        import ray
    except ImportError:
        raise InputError(
            "--executor ray needs the optional extra: "
            "pip install 'fabric-imitation[ray]'"
        ) from None
    if not ray.is_initialized():
        ray.init(num_cpus=workers, include_dashboard=False, log_to_driver=False)
    return ray


def RunJobs(
    run: Callable,
    jobs: Iterable,
    *,
    workers: int,
    executor: str = "local",
    init: Callable | None = None,
    init_args: tuple = (),
    tasks_per_worker: int = 0,
    ordered: bool = True,
) -> Iterator:
    """Yields run(job) for each job, in the jobs' order when `ordered`, else
    as they finish.

    executor "local": in this process when workers == 1 and
    tasks_per_worker == 0; otherwise in `workers` spawned processes, each
    replaced after `tasks_per_worker` jobs (0: never), which keeps a long
    sweep's memory flat. "ray": on `workers` Ray actors (a running cluster
    if `ray` is connected).
    """
    if executor not in EXECUTORS:
        raise InputError(f"unknown executor {executor!r}; use local or ray")
    if executor == "ray":
        yield from _ray(run, jobs, workers, init, init_args, ordered)
    elif workers == 1 and tasks_per_worker == 0:
        if init is not None:
            init(*init_args)
        for job in jobs:
            yield run(job)
    else:
        with mp.get_context("spawn").Pool(
            workers,
            initializer=init,
            initargs=init_args,
            maxtasksperchild=tasks_per_worker or None,
        ) as pool:
            # Leaving the with block (also on the generator's close)
            # terminates the workers.
            yield from (pool.imap if ordered else pool.imap_unordered)(run, jobs)


def _ray(run, jobs, workers, init, init_args, ordered) -> Iterator:
    ray = StartRay(workers)
    from ray.util import ActorPool

    @ray.remote(num_cpus=1)
    class Worker:
        def __init__(self, *args):
            if init is not None:
                init(*args)

        def run(self, job):
            return run(job)

    # Shared once through the object store, not copied per actor.
    args = [ray.put(a) for a in init_args]
    pool = ActorPool([Worker.remote(*args) for _ in range(workers)])
    todo = iter(jobs)
    pending = 0

    def submit() -> bool:
        job = next(todo, _END)
        if job is _END:
            return False
        pool.submit(lambda actor, j: actor.run.remote(j), job)
        return True

    try:
        for _ in range(2 * workers):
            pending += submit()
        while pending:
            result = pool.get_next() if ordered else pool.get_next_unordered()
            pending -= 1
            yield result
            pending += submit()
    finally:
        while pool.has_next():
            pool.get_next_unordered()


_END = object()
