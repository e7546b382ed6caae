"""Independent runs of an experiment in worker processes (``smartedge evaluate paper --jobs``).

A run of the paper's experiments depends only on its seed and its settings, never on the runs
before it, so the runs of one experiment can go to a process pool and come back in the order
they were planned: the tables of ``--jobs 2`` are those of ``--jobs 1``, number for number
(``tests/lab/experiments/test_parallel.py``).

Workers are started with ``spawn`` (a fresh interpreter: no GL context, onnxruntime thread pool
or GTSAM state is inherited from the parent) and build their own state once, in
:func:`map_runs`'s ``make_state`` (the world, the detection source); each task is one run.
What a worker needs is pickled once per pool (:func:`dumps_portable`: a scenario's site holds
read-only mappings, which plain pickle refuses).
"""

from __future__ import annotations

import concurrent.futures
import logging
import multiprocessing
import os
import pickle
from collections.abc import Callable, Iterator, Sequence
from types import MappingProxyType
from typing import Any, TypeVar

log = logging.getLogger(__name__)

S = TypeVar("S")
T = TypeVar("T")
R = TypeVar("R")

#: the worker process's state and run function (set by the pool's initializer, per process)
_worker_state: Any = None
_worker_run: Callable[[Any, Any], Any] | None = None


def default_jobs() -> int:
    """Worker processes by default: the cores this process may run on."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


def resolve_jobs(requested: int | None, runs: int, payload: tuple[Any, ...] = ()) -> int:
    """Processes for ``runs`` runs: ``requested`` (``None``: :func:`default_jobs`), at most one
    per run, at least 1; 1 when something of ``payload`` (what the workers need) cannot be
    sent to another process (logged)."""
    jobs = default_jobs() if requested is None else int(requested)
    jobs = max(1, min(jobs, runs))
    if jobs > 1 and not picklable(payload):
        log.warning("what the runs need cannot be sent to worker processes (a lambda as the "
                    "fusion factory?): the %d runs run in this process", runs)
        return 1
    return jobs


def _mapping_proxy(mapping: dict[str, Any]) -> MappingProxyType[str, Any]:
    return MappingProxyType(mapping)


class _PortablePickler(pickle.Pickler):
    """Pickles read-only mappings (``types.MappingProxyType``) as what they wrap."""

    def reducer_override(self, obj: Any) -> Any:
        if type(obj) is MappingProxyType:
            return _mapping_proxy, (dict(obj),)
        return NotImplemented


def dumps_portable(obj: Any) -> bytes:
    """``pickle.dumps(obj)`` that also takes read-only mappings (a :class:`core.site.Site`'s
    sections); ``pickle.loads`` reads it back."""
    import io

    buf = io.BytesIO()
    _PortablePickler(buf, protocol=pickle.HIGHEST_PROTOCOL).dump(obj)
    return buf.getvalue()


def picklable(obj: Any) -> bool:
    """Whether ``obj`` can be sent to a worker process (a lambda cannot, a class can)."""
    try:
        dumps_portable(obj)
    except (pickle.PicklingError, TypeError, AttributeError):
        return False
    return True


def _init_worker(payload: bytes) -> None:
    global _worker_state, _worker_run
    make_state, args, run = pickle.loads(payload)
    _worker_state = make_state(*args)
    _worker_run = run


def _run_task(task: Any) -> Any:
    assert _worker_run is not None, "the pool's initializer did not run"
    return _worker_run(_worker_state, task)


def map_runs(run: Callable[[S, T], R], tasks: Sequence[T], jobs: int,
             make_state: Callable[..., S], state_args: tuple[Any, ...]) -> Iterator[R]:
    """``run(state, task)`` for every task, results in the order of ``tasks``.

    ``jobs`` 1: in this process, one state (``make_state(*state_args)``) for all tasks.
    Otherwise ``jobs`` spawned worker processes, each with its own state built the same way;
    ``run``, ``make_state`` and ``state_args`` must be picklable (module-level functions,
    classes, data). A worker's exception is raised here when its result is reached."""
    if jobs <= 1 or len(tasks) <= 1:
        state = make_state(*state_args)
        for task in tasks:
            yield run(state, task)
        return
    payload = dumps_portable((make_state, state_args, run))
    log.info("%d runs in %d worker processes", len(tasks), jobs)
    pool = concurrent.futures.ProcessPoolExecutor(
        max_workers=jobs, mp_context=multiprocessing.get_context("spawn"),
        initializer=_init_worker, initargs=(payload,))
    try:
        futures = [pool.submit(_run_task, task) for task in tasks]
        for future in futures:
            yield future.result()
    finally:
        pool.shutdown(wait=True, cancel_futures=True)
