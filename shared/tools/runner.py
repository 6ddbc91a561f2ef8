"""Independent jobs of an experiment (training a team) run in parallel: in this process, in local
worker processes, or as tasks on an existing Dask distributed cluster (`dask scheduler` /
`dask worker`; the ``cluster`` extra).

A job is a module-level function and its arguments (picklable, so that another process or
machine can run it) that returns the files it made as {relative path: bytes}; the caller writes
them under its own results directory, so workers need no shared file system. A job fixes its
own torch thread count (``JOB_THREADS``): floating-point sums depend on it, and the same seeds
must give the same numbers whichever way the jobs run. Finished jobs are what the experiments'
cache holds, so a killed run resumes from them.
"""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import multiprocessing
import os
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from shared.core.files import atomic_write

JOB_THREADS = 1  # torch threads inside every job, in every mode


@dataclass(frozen=True)
class Job:
    """``fn(*args)`` -> {path relative to the results directory: bytes}. ``key`` names the job (two
    jobs with one key are one job); ``weight`` is its expected cost, for the ETA."""

    key: str
    label: str
    fn: Callable[..., dict[str, bytes]]
    args: tuple[Any, ...] = field(default=())
    weight: float = 1.0


def _call(job: Job) -> dict[str, bytes]:
    import torch

    torch.set_num_threads(JOB_THREADS)
    return job.fn(*job.args)


def _results(
    jobs: list[Job], workers: int, scheduler: str | None, starting: Callable[[Job], None] = lambda _j: None
) -> Iterator[tuple[Job, dict[str, bytes]]]:
    """(job, files) as the jobs finish; in this process, ``starting`` is told of each job first."""
    if scheduler:
        try:
            from distributed import Client, as_completed
        except ModuleNotFoundError:
            raise ValueError(
                "--dask-scheduler needs dask and distributed: pip install 'mures-fleet[cluster]'"
            ) from None
        try:
            client = Client(scheduler, timeout=15)
        except OSError as exc:
            raise ValueError(f"cannot reach the Dask scheduler at {scheduler}: {exc}") from None
        try:
            futures = {client.submit(_call, j, key=f"mures-{j.key}", pure=False): j for j in jobs}
            for fut in as_completed(futures):
                yield futures[fut], fut.result()
        finally:
            client.close()
    elif workers > 1:
        # spawn: a forked torch process can deadlock on the parent's thread pools
        with cf.ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn")) as pool:
            pending = {pool.submit(_call, j): j for j in jobs}
            for fut in cf.as_completed(pending):
                yield pending[fut], fut.result()
    else:
        import torch

        threads = torch.get_num_threads()
        try:
            for j in jobs:
                starting(j)
                yield j, _call(j)
        finally:
            torch.set_num_threads(threads)  # this process's own setting again


def run_jobs(
    jobs: list[Job],
    root: Path,
    workers: int = 1,
    scheduler: str | None = None,
    say: Callable[[str], None] = print,
) -> None:
    """Run the jobs (``workers`` local processes, or the Dask cluster at ``scheduler``), writing
    each one's files under ``root`` as it finishes, with a progress line and an ETA."""
    unique = list({j.key: j for j in jobs}.values())
    if not unique:
        return
    if workers < 1:
        raise ValueError(f"--workers must be at least 1, got {workers}")
    where = f"Dask scheduler {scheduler}" if scheduler else f"{workers} local process{'es' if workers > 1 else ''}"
    if len(unique) == 1:  # say what is running before a long job starts, not only when it ends
        say(f"{unique[0].label} (on {where})")
    else:
        say(f"{len(unique)} jobs to run on {where}")
    total = sum(j.weight for j in unique)
    done_w, t0 = 0.0, time.perf_counter()
    sequential = workers == 1 and not scheduler and len(unique) > 1
    starting = (lambda j: say(f"{j.label} ...")) if sequential else (lambda _j: None)
    for k, (job, files) in enumerate(_results(unique, workers, scheduler, starting), 1):
        # a snapshot's policy.json marks it complete in the cache: written last
        for rel in sorted(files, key=lambda r: (Path(r).name == "policy.json", r)):
            (root / rel).parent.mkdir(parents=True, exist_ok=True)
            atomic_write(root / rel, files[rel])
        done_w += job.weight
        elapsed = time.perf_counter() - t0
        eta = elapsed * (total - done_w) / done_w if done_w else float("nan")
        say(f"[{k}/{len(unique)}] {job.label} done; {elapsed:.0f} s elapsed, ETA {eta:.0f} s")


def directory_files(path: Path, rel_to: Path) -> dict[str, bytes]:
    """Every file under ``path`` as {path relative to ``rel_to``: bytes}."""
    return {str(p.relative_to(rel_to)): p.read_bytes() for p in sorted(path.rglob("*")) if p.is_file()}


@contextlib.contextmanager
def local_dask_cluster(workers: int, workdir: Path, project: Path) -> Iterator[str]:
    """A Dask scheduler and ``workers`` one-thread workers on loopback, started with the
    `dask scheduler` / `dask worker` commands as on a real cluster (``project``: the checkout the
    workers import from); yields the scheduler's address and stops them all on exit. The workers
    run without a nanny: nothing here restarts them, and a nanny's worker process takes 8 s to
    stop on SIGTERM (the nanny's own timeout) where a worker without one stops at once."""
    from distributed import Client

    from shared.tools.fleetsim import free_port, reap, wait_until

    port = free_port()
    address = f"tcp://127.0.0.1:{port}"
    env = {**os.environ, "PYTHONPATH": str(project), "OMP_NUM_THREADS": "1"}
    dask = str(Path(sys.executable).parent / "dask")
    quiet: dict[str, Any] = {"env": env, "cwd": workdir, "stdout": subprocess.DEVNULL, "stderr": subprocess.DEVNULL}
    procs = [
        subprocess.Popen([dask, "scheduler", "--host", "127.0.0.1", "--port", str(port), "--no-dashboard"], **quiet)
    ]
    try:
        for i in range(workers):
            local = str(workdir / f"worker-{i}")
            worker = [dask, "worker", address, "--nthreads", "1", "--no-dashboard", "--no-nanny"]
            procs.append(subprocess.Popen([*worker, "--local-directory", local], **quiet))
        with Client(address, timeout=60) as client:
            wait_until(lambda: len(client.scheduler_info()["workers"]) == workers, 120, f"{workers} Dask workers")
        yield address
    finally:
        # the workers first, then the scheduler: a worker whose scheduler has gone waits to reconnect
        for group in (procs[1:], procs[:1]):
            for p in group:
                p.terminate()
            for p in group:
                reap(p, 30)
