"""Run independent per-object tasks in parallel: a process pool (concurrent.futures) by
default, or Ray. Results are handed to ``on_result`` in the parent process as they finish
(so the parent is the only writer of the manifest); a tqdm bar shows progress."""

from __future__ import annotations

import multiprocessing
import os
from collections.abc import Callable, Sequence
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait


class RayNotInstalled(RuntimeError):
    pass


def default_workers() -> int:
    """One worker per CPU core available to this process."""
    try:
        return max(len(os.sched_getaffinity(0)), 1)
    except AttributeError:  # pragma: no cover - not Linux
        return os.cpu_count() or 1


def _bar(total: int, progress: bool, desc: str):
    from tqdm import tqdm

    return tqdm(total=total, disable=not progress, unit="obj", desc=desc, dynamic_ncols=True)


def run_tasks(
    fn: Callable,
    tasks: Sequence[tuple],
    workers: int = 1,
    use_ray: bool = False,
    on_result: Callable[[object], str | None] = lambda r: None,
    progress: bool = True,
    desc: str = "objects",
) -> None:
    """Call ``fn(*task)`` for every task; ``on_result(result)`` runs in this process as each
    finishes (its return value, if any, is shown beside the progress bar).

    ``workers`` <= 1 without Ray runs in this process (no pool). With ``use_ray`` the same
    tasks run as Ray remote functions on ``workers`` CPUs of a local Ray instance (or the
    cluster named by RAY_ADDRESS)."""
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    if use_ray:
        _run_ray(fn, tasks, workers, on_result, progress, desc)
        return
    bar = _bar(len(tasks), progress, desc)
    try:
        if workers == 1 or len(tasks) <= 1:
            for t in tasks:
                _report(bar, on_result(fn(*t)))
            return
        ctx = multiprocessing.get_context("spawn")  # no fork of a process holding threads / native state
        with ProcessPoolExecutor(max_workers=min(workers, len(tasks)), mp_context=ctx) as pool:
            pending = {pool.submit(fn, *t) for t in tasks}
            try:
                while pending:
                    done, pending = wait(pending, return_when=FIRST_COMPLETED)
                    for f in done:
                        _report(bar, on_result(f.result()))
            except BaseException:
                for f in pending:
                    f.cancel()
                raise
    finally:
        bar.close()


def _report(bar, msg) -> None:
    bar.update(1)
    if msg:
        bar.set_postfix_str(msg, refresh=False)


def _import_ray():
    try:
        import ray
    except ImportError as e:
        raise RayNotInstalled("--ray needs Ray, which is not installed: pip install vgq-cnn[ray]") from e
    return ray


def _run_ray(fn, tasks, workers, on_result, progress, desc) -> None:
    ray = _import_ray()
    started = False
    if not ray.is_initialized():
        kw = {} if os.environ.get("RAY_ADDRESS") else {"num_cpus": workers}
        ray.init(include_dashboard=False, log_to_driver=False, **kw)
        started = True
    bar = _bar(len(tasks), progress, desc + " (ray)")
    try:
        remote = ray.remote(num_cpus=1)(fn)
        pending = [remote.remote(*t) for t in tasks]
        while pending:
            done, pending = ray.wait(pending, num_returns=1)
            for ref in done:
                _report(bar, on_result(ray.get(ref)))
    finally:
        bar.close()
        if started:
            ray.shutdown()
