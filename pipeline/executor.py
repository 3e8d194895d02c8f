"""The executors of `cli prepare` (`run_local` also writes the logs of `cli synth --workers`): each runs
the work it is given for one log on every log, and returns the results in log order. `run_local`: this
process, or a fork pool; `run_ray` (`--executor ray`): one Ray task per log, on a local instance or on a
running cluster.

Each task runs the work it is given for one log (`cli prepare`: `prepare_log`), which writes the log's
shards itself, exactly as the local executor does, so the shards are the same bytes; `root` and `out`
must be on a filesystem that every node sees, and every node needs this package installed (the same as
the driver's). Results come back in job order (on_done as each log finishes), so errors.jsonl and the
manifest are the same as a local run's. Ray enables token authentication for the
clusters it starts; a driver joining one by HOST:PORT (not "auto") sends the token only with
RAY_AUTH_MODE=token set (Ray's rule: an explicit address never turns it on by itself).

Heavy devkit objects are loaded once per worker process, not once per task: Ray keeps its worker
processes and runs task after task in them, so the adapters' module-level caches (`nuscenes._tables`,
keyed by version and dataroot; `nuscenes.open_map`, keyed by dataroot and map) stay loaded between the
tasks a worker runs. The object store was the other way: but the NuScenes tables are a graph of Python
dicts, not arrays, so every task would unpickle its own ~1 GB copy from it (zero-copy reads are for
numpy buffers only); per-worker loading pays that once per process.
"""

from __future__ import annotations

import functools
import logging
import multiprocessing
from collections.abc import Callable

from pipeline.errors import DataError

INSTALL_HINT = "--executor ray needs Ray, an optional extra: pip install -e '.[ray]' (or pip install ray)"


class RayMissing(ImportError):
    pass


def import_ray():
    try:
        import ray
    except ImportError as error:
        raise RayMissing(INSTALL_HINT) from error
    return ray


def run_local(jobs: list, work: Callable, workers: int, on_done: Callable) -> list:
    """work(job) of every job, results in job order: in this process (workers <= 1) or in a fork pool of
    `workers` (its processes inherit what this one has loaded); on_done(job, its result) as each finishes."""
    results = []
    if workers <= 1:
        for job in jobs:
            results.append(work(job))
            on_done(job, results[-1])
        return results
    results = [None] * len(jobs)
    with multiprocessing.get_context("fork").Pool(workers) as pool:
        # as each finishes (imap's job order would hold a finished log's on_done back behind a slow one)
        for i, result in pool.imap_unordered(functools.partial(numbered, work), enumerate(jobs)):
            results[i] = result
            on_done(jobs[i], result)
    return results


def numbered(work: Callable, item: tuple) -> tuple:
    """(i, work(job)) of a pool's (i, job)."""
    i, job = item
    return i, work(job)


def run_task(work: Callable, job):
    """work(job) in a Ray worker: (its result, None), or (None, the DataError's fields): a DataError does
    not unpickle whole (its constructor takes three arguments), so it travels as its parts."""
    try:
        return work(job), None
    except DataError as error:
        return None, (error.source, error.record, error.problem)


def run_ray(jobs: list, work: Callable, workers: int, address: str | None, on_done: Callable) -> list:
    """work(job) of every job (a picklable callable that does one log and writes its shards), results in
    job order; on_done(job, its result) as each log finishes. address: None starts a local instance with
    `workers` CPUs, "auto" or HOST:PORT joins a running cluster (`ray start --head`). A Ray already
    initialised by the caller is used as it is and left running."""
    ray = import_ray()
    started = not ray.is_initialized()
    if started:  # "local": a new instance, even where a `ray start` cluster runs on this machine
        cpus = None if address else max(workers, 1)
        ray.init(address or "local", num_cpus=cpus, log_to_driver=False, logging_level=logging.WARNING)
    try:
        task = ray.remote(num_cpus=1)(run_task)
        refs = [task.remote(work, job) for job in jobs]
        index = {ref: i for i, ref in enumerate(refs)}
        results = [None] * len(jobs)
        pending = list(refs)
        while pending:
            (ref,), pending = ray.wait(pending, num_returns=1)
            result, error = ray.get(ref)
            if error:  # the other tasks are not cancelled (Ray's cancel interrupts workers mid-task): a
                # local instance ends with them at shutdown; on a cluster they finish whole shards
                raise DataError(*error)
            results[index[ref]] = result
            on_done(jobs[index[ref]], result)
        return results
    finally:
        if started:
            ray.shutdown()
