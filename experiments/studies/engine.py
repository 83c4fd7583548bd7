"""Run many independent tasks on the local cores or on a Ray cluster.

`run_tasks(fn, tasks, engine=...)` returns `[fn(t) for t in tasks]` in task order,
whichever engine runs them, and calls `progress(done, total)` as each finishes.

- `local`: a `concurrent.futures.ProcessPoolExecutor` with `workers` processes (default
  `os.cpu_count()`), started with "spawn" so each worker begins from a fresh interpreter
  (as a Ray worker does); `workers=1` runs the tasks in this process, one by one.
- `ray`: one Ray task per item (`num_cpus=1` each). With `address` it joins an existing
  cluster (`ray.init(address=...)`, e.g. "auto" or "ray://head:10001"; the nodes need
  walker-slam installed, same version); without, it starts a local Ray instance with
  `workers` CPUs (no dashboard) and shuts it down afterwards. Its workers run at this
  process's priority, as the local engine's do: Ray's default niceness of 15 leaves them a
  few per cent of a core beside any other busy process (a study's two runs: 1.9 s on an
  idle machine, 66 s beside three busy loops).

`fn` must be importable by name (a module-level function) and the tasks picklable. The
tasks are deterministic (every run is seeded), so both engines give identical results.
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import socket
from collections.abc import Callable, Sequence
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from typing import Any, TypeVar

from hardware.errors import ConfigError

T = TypeVar("T")
R = TypeVar("R")

ENGINES = ("local", "ray")


def default_workers() -> int:
    return os.cpu_count() or 1


def check(engine: str, workers: int | None, address: str | None) -> None:
    """ValueError for an unknown engine, workers < 1, an address without Ray or a Ray
    address that does not answer."""
    if engine not in ENGINES:
        raise ConfigError(f"unknown engine '{engine}'; valid: {', '.join(ENGINES)}")
    if workers is not None and workers < 1:
        raise ConfigError(f"workers must be >= 1, got {workers}")
    if address is not None and engine != "ray":
        raise ConfigError("--address is for --engine ray")
    if address:
        _reachable(address)


def run_tasks(
    fn: Callable[[T], R],
    tasks: Sequence[T],
    *,
    engine: str = "local",
    workers: int | None = None,
    address: str | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> list[R]:
    """`[fn(t) for t in tasks]`, run by `engine`; see the module docstring."""
    check(engine, workers, address)
    workers = default_workers() if workers is None else workers
    tasks = list(tasks)
    if not tasks:
        return []
    if engine == "ray":
        return _run_ray(fn, tasks, workers, address, progress)
    return _run_local(fn, tasks, workers, progress)


def _run_local(fn, tasks, workers, progress) -> list:
    n = len(tasks)
    results: list[Any] = [None] * n
    if workers == 1 or n == 1:
        for i, t in enumerate(tasks):
            results[i] = fn(t)
            if progress is not None:
                progress(i + 1, n)
        return results
    ctx = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(max_workers=min(workers, n), mp_context=ctx) as pool:
        futures = {pool.submit(fn, t): i for i, t in enumerate(tasks)}
        pending = set(futures)
        done_count = 0
        try:
            while pending:
                done, pending = wait(pending, return_when=FIRST_COMPLETED)
                for f in done:
                    results[futures[f]] = f.result()  # re-raises a task's exception
                    done_count += 1
                    if progress is not None:
                        progress(done_count, n)
        except BaseException:
            for f in pending:
                f.cancel()
            raise
    return results


def _reachable(address: str, timeout_s: float = 5.0) -> None:
    """ValueError unless `address` ("host:port", optionally "ray://host:port") accepts a
    TCP connection: Ray itself retries an unreachable cluster for minutes. Other forms
    ("auto", "local") are left to Ray."""
    host, sep, port = address.removeprefix("ray://").rpartition(":")
    if not sep or not port.isdigit() or not host:
        return
    try:
        socket.create_connection((host, int(port)), timeout=timeout_s).close()
    except OSError as e:
        raise ConfigError(f"cannot reach the Ray cluster at {address}: {e}") from None


def _run_ray(fn, tasks, workers, address, progress) -> list:
    try:
        import ray
    except ImportError:  # pragma: no cover - ray is a dependency
        raise ConfigError("--engine ray needs the 'ray' package (pip install ray)") from None
    started = False
    if not ray.is_initialized():
        if address:
            ray.init(address=address, logging_level=logging.WARNING, log_to_driver=False)
        else:
            ray.init(
                num_cpus=workers,
                include_dashboard=False,
                logging_level=logging.WARNING,
                log_to_driver=False,
                _system_config={"worker_niceness": 0},
            )
        started = True
    try:
        remote = ray.remote(num_cpus=1, max_retries=0)(fn)
        refs = [remote.remote(t) for t in tasks]
        index = {ref: i for i, ref in enumerate(refs)}
        results: list[Any] = [None] * len(tasks)
        pending = list(refs)
        done_count = 0
        while pending:
            done, pending = ray.wait(pending, num_returns=1)
            for ref in done:
                results[index[ref]] = ray.get(ref)
                done_count += 1
                if progress is not None:
                    progress(done_count, len(tasks))
        return results
    finally:
        if started:
            ray.shutdown()
