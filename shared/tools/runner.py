"""Independent jobs of an experiment (training a team) run in parallel: in this process, in local
worker processes, or as tasks on an existing Dask distributed cluster (`dask scheduler` /
`dask worker`; the ``cluster`` extra).

A job is a module-level function and its arguments (picklable, so that another process or
machine can run it) that returns the files it made as {relative path: bytes}; the caller writes
them under its own results directory, so workers need no shared file system. A job fixes its
own torch thread count (``JOB_THREADS``): floating-point sums depend on it, and the same seeds
must give the same numbers whichever way the jobs run. Finished jobs are what the experiments'
cache holds, so a killed run resumes from them; a MARL team's training, the longest job, also
resumes from its own last checkpoint (``Job.checkpoint``), so hours of it are not lost with it.
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
# a job's weight is its estimated seconds on one core (the experiments' estimates); the 38 teams
# of the committed protocol cache took 0.6 to 1.7 times theirs (median 0.94; wall_seconds in each
# training_summary.json), the slowest an N = 1 MAMBPO team beside two other jobs: a deadline
# admits a job only if 1.7 times its weight still fits
UNTIL_MARGIN = 1.7
# with jobs running elsewhere (local processes, a cluster), a line saying what is still running
# after every HEARTBEAT_S seconds in which none finished: a team can take an hour
HEARTBEAT_S = 600.0


@dataclass(frozen=True)
class Job:
    """``fn(*args)`` -> {path relative to the results directory: bytes}. ``key`` names the job (two
    jobs with one key are one job); ``weight`` is its expected cost, for the ETA. A job that
    ``reports`` (a team's training, a cell's evaluation) is called as
    ``fn(*args, progress=JobProgress(label))`` and tells it how far it has got. A job with a
    ``checkpoint`` directory is also given ``checkpoint=`` it: a team's training saves its state
    there as it goes and, started again after being killed, continues from it."""

    key: str
    label: str
    fn: Callable[..., dict[str, bytes]]
    args: tuple[Any, ...] = field(default=())
    weight: float = 1.0
    reports: bool = False
    checkpoint: str | None = None


class JobProgress:
    """A long job's progress (a team's training, a planner's cell), told from inside the job
    wherever it runs (this process, a local worker process, a Dask worker's log): after every
    ``every_s`` seconds, one stderr line with the episodes done, the rate and the time left at that
    rate. A job shorter than ``every_s`` says nothing, so quick runs stay quiet; an hour-long team
    says where it is six times. Called with the trainers' and ``evaluate``'s progress dicts
    (``episodes``, ``total``, ``episodes_per_second``)."""

    def __init__(self, label: str, every_s: float = HEARTBEAT_S, stream: Any = None) -> None:
        self.label, self.every_s, self.stream = label, every_s, stream
        self.t0 = self.last = time.perf_counter()

    def __call__(self, p: dict[str, Any]) -> None:
        now = time.perf_counter()
        if now - self.last < self.every_s or p["episodes"] >= p["total"]:
            return
        self.last = now
        rate = p["episodes_per_second"]
        left = (p["total"] - p["episodes"]) / max(rate, 1e-9)
        print(
            f"{self.label}: {p['episodes']:,}/{p['total']:,} episodes ({100 * p['episodes'] / p['total']:.0f} %)"
            f" in {_minutes(now - self.t0)}, {_rate(rate)}, about {_minutes(left)} left",
            file=self.stream or sys.stderr,
            flush=True,
        )


def _call(job: Job) -> dict[str, bytes]:
    import torch

    torch.set_num_threads(JOB_THREADS)
    kwargs: dict[str, Any] = {}
    if job.reports:
        kwargs["progress"] = JobProgress(job.label)
    if job.checkpoint is not None:
        kwargs["checkpoint"] = job.checkpoint
    return job.fn(*job.args, **kwargs)


def _results(
    jobs: list[Job],
    workers: int,
    scheduler: str | None,
    starting: Callable[[Job], None] = lambda _j: None,
    admit: Callable[[Job], bool] | None = None,
    skipped: list[Job] | None = None,
    waiting: Callable[[], None] = lambda: None,
    wait_s: float | None = None,
) -> Iterator[tuple[Job, dict[str, bytes]]]:
    """(job, files) as the jobs finish. ``starting`` is told of each job as it gets a worker (in
    this process, before it runs; on a Dask cluster only with ``admit``, where jobs go out as
    threads free up: without it they all go to the scheduler at once). With ``admit``, a job starts
    only when a worker is free and ``admit(job)`` says yes at that moment (a deadline); the jobs it
    refuses go to ``skipped``, unrun. With ``wait_s``, ``waiting`` is called after every ``wait_s``
    seconds in which no job finished (on other processes or a cluster; a job running in this
    process blocks it)."""

    def admitted(queue: list[Job]) -> Job | None:  # the next job to start, refused ones set aside
        while queue:
            j = queue.pop(0)
            if admit is None or admit(j):
                return j
            if skipped is not None:
                skipped.append(j)
        return None

    if scheduler:
        try:
            from distributed import Client, wait
        except ModuleNotFoundError:
            raise ValueError(
                "--dask-scheduler needs dask and distributed: pip install 'mures-fleet[cluster]'"
            ) from None
        try:
            client = Client(scheduler, timeout=15)
        except OSError as exc:
            raise ValueError(f"cannot reach the Dask scheduler at {scheduler}: {exc}") from None
        try:
            queue = list(jobs)
            # without a deadline every job goes to the scheduler at once; with one, as many as the
            # cluster has threads, the next when one finishes (so that each is admitted then)
            slots = len(queue) if admit is None else max(1, sum(client.nthreads().values()))
            futures: dict[Any, Job] = {}  # distributed.Future -> its job

            def submit(j: Job) -> None:
                futures[client.submit(_call, j, key=f"mures-{j.key}", pure=False)] = j
                if admit is not None:
                    starting(j)

            while len(futures) < slots and (j := admitted(queue)) is not None:
                submit(j)
            while futures:
                try:
                    finished, _ = wait(list(futures), timeout=wait_s, return_when="FIRST_COMPLETED")
                except TimeoutError:
                    waiting()
                    continue
                for fut in finished:
                    job = futures.pop(fut)
                    if (j := admitted(queue)) is not None:
                        submit(j)
                    yield job, fut.result()
        finally:
            client.close()
    elif workers > 1:
        # spawn: a forked torch process can deadlock on the parent's thread pools
        with cf.ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn")) as pool:
            queue = list(jobs)
            pending: dict[cf.Future[dict[str, bytes]], Job] = {}

            def start(j: Job) -> None:
                pending[pool.submit(_call, j)] = j
                starting(j)

            while len(pending) < workers and (j := admitted(queue)) is not None:
                start(j)
            while pending:
                finished, _ = cf.wait(pending, timeout=wait_s, return_when=cf.FIRST_COMPLETED)
                if not finished:
                    waiting()
                for fut in finished:
                    job = pending.pop(fut)
                    if (j := admitted(queue)) is not None:
                        start(j)
                    yield job, fut.result()
    else:
        import torch

        threads = torch.get_num_threads()
        try:
            queue = list(jobs)
            while (j := admitted(queue)) is not None:
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
    until: float | None = None,
    heartbeat_s: float = HEARTBEAT_S,
) -> list[Job]:
    """Run the jobs (``workers`` local processes, or the Dask cluster at ``scheduler``), writing
    each one's files under ``root`` as it finishes, with a progress line and an ETA; on other
    processes a line as each job starts and, after every ``heartbeat_s`` seconds in which none
    finished, one saying what is still running, for how long, against its estimate. With
    ``until`` (a time.time() instant) the jobs go longest first and none starts whose estimate,
    ``UNTIL_MARGIN`` x its weight in seconds, would end past it: a job cut off mid-way would be
    lost (a job's files are written only when it ends; a job with a checkpoint keeps its progress
    up to its last one). Returns the jobs left unrun, [] without ``until``."""
    unique = list({j.key: j for j in jobs}.values())
    if not unique:
        return []
    if workers < 1:
        raise ValueError(f"--workers must be at least 1, got {workers}")
    admit = None
    if until is not None:
        unique.sort(key=lambda j: -j.weight)  # longest first: the short ones fill in before the deadline

        def admit(j: Job) -> bool:
            return time.time() + UNTIL_MARGIN * j.weight <= until

    where = f"Dask scheduler {scheduler}" if scheduler else f"{workers} local process{'es' if workers > 1 else ''}"
    if len(unique) == 1:  # say what is running before a long job starts, not only when it ends
        say(f"{unique[0].label} (on {where})")
    else:
        say(f"{len(unique)} jobs to run on {where}")
    skipped: list[Job] = []
    total = sum(j.weight for j in unique)
    done_w, t0 = 0.0, time.perf_counter()
    here = workers == 1 and not scheduler
    running: dict[str, tuple[Job, float]] = {}  # key -> (job, when it started), on other processes

    def starting(j: Job) -> None:
        if here:
            if len(unique) > 1:
                say(f"{j.label} ...")
            return
        running[j.key] = (j, time.perf_counter())
        if len(unique) > 1:  # a single job was named above
            say(f"started: {j.label}")

    def waiting() -> None:
        now = time.perf_counter()
        if running:
            say(
                "still running: "
                + "; ".join(
                    f"{j.label} ({_minutes(now - t)}, estimate {_minutes(j.weight)})" for j, t in running.values()
                )
            )
        else:  # a cluster given every job at once: which of them run is the scheduler's business
            say(f"{len(unique) - k_done - len(skipped)} jobs not finished on {where}, {_minutes(now - t0)} elapsed")

    k_done = 0
    results = _results(unique, workers, scheduler, starting, admit, skipped, waiting, None if here else heartbeat_s)
    for k, (job, files) in enumerate(results, 1):
        k_done = k
        running.pop(job.key, None)
        # a snapshot's policy.json marks it complete in the cache: written last
        for rel in sorted(files, key=lambda r: (Path(r).name == "policy.json", r)):
            (root / rel).parent.mkdir(parents=True, exist_ok=True)
            atomic_write(root / rel, files[rel])
        done_w += job.weight
        elapsed = time.perf_counter() - t0
        left_w = total - done_w - sum(j.weight for j in skipped)
        eta = elapsed * left_w / done_w if done_w else float("nan")
        say(f"[{k}/{len(unique) - len(skipped)}] {job.label} done; {elapsed:.0f} s elapsed, ETA {eta:.0f} s")
    if skipped:
        say(
            f"{len(skipped)} of {len(unique)} jobs not started: their estimates would run past the deadline "
            f"({sum(j.weight for j in skipped) / 3600:.1f} h on one core): {'; '.join(j.label for j in skipped)}"
        )
    return skipped


def _minutes(seconds: float) -> str:
    return f"{seconds / 60:.0f} min"


def _rate(per_second: float) -> str:
    """Episodes per second, or per minute for a planner's slow ones (a MILP cell: 3 a minute)."""
    return f"{per_second:.0f} episodes/s" if per_second >= 1 else f"{60 * per_second:.1f} episodes/min"


def directory_files(path: Path, rel_to: Path) -> dict[str, bytes]:
    """Every file under ``path`` as {path relative to ``rel_to``: bytes}."""
    return {str(p.relative_to(rel_to)): p.read_bytes() for p in sorted(path.rglob("*")) if p.is_file()}


@contextlib.contextmanager
def local_dask_cluster(workers: int, workdir: Path, project: Path) -> Iterator[str]:
    """A Dask scheduler and ``workers`` one-thread workers on loopback, started with the
    `dask scheduler` / `dask worker` commands as on a real cluster (``project``: the checkout the
    workers import from, ahead of any PYTHONPATH of the caller's); yields the scheduler's address
    and stops them all on exit. The workers run without a nanny: nothing here restarts them, and a
    nanny's worker process takes 8 s to stop on SIGTERM (the nanny's own timeout) where a worker
    without one stops at once."""
    from distributed import Client

    from shared.tools.fleetsim import free_port, reap, wait_until

    port = free_port()
    address = f"tcp://127.0.0.1:{port}"
    path = os.pathsep.join(p for p in (str(project), os.environ.get("PYTHONPATH", "")) if p)  # the caller's after it
    env = {**os.environ, "PYTHONPATH": path, "OMP_NUM_THREADS": "1"}
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
