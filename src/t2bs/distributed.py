"""Run independent jobs (one per expression video, paper appendix) in-process, on a local process
pool, or on a Ray cluster, with exactly-once results in the project folder.

A job is a picklable description: a content key of its inputs + config, the folder its results
belong in, and an importable function ``fn(staging_dir: Path, **kwargs) -> dict``. Each attempt
writes into its own fresh staging folder beside the final one; only the driver commits a
finished attempt (rename staging -> final, then ``done.json``). So a worker killed mid-job, a
retried task or a Ctrl-C never leaves a half-written result that looks finished, and a re-run
(same keys) skips every committed job.
"""

from __future__ import annotations

import importlib
import os
import shutil
import time
import uuid
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from tqdm import tqdm

from t2bs.errors import UserError
from t2bs.openmp import shared_cores
from t2bs.project import is_done, mark_done

EXECUTORS = ("local", "process", "ray")


@dataclass
class Job:
    key: str  # content key of the job's inputs and config (t2bs.project.content_key)
    name: str  # short label for progress and reports, e.g. "recon/blinking-s0"
    out_dir: Path  # final folder of the results; holds done.json once committed
    fn: str  # "package.module:function", called as fn(staging_dir, **kwargs) -> dict of info
    kwargs: dict = field(default_factory=dict)  # picklable arguments
    num_cpus: float = 1.0  # Ray resource request
    num_gpus: float = 0.0  # Ray resource request (a GPU backend asks for 1)


def resolve(fn: str) -> Callable[..., dict]:
    module, _, name = fn.partition(":")
    return getattr(importlib.import_module(module), name)


def execute_attempt(job: Job, threads: int | None = None) -> dict:
    """Run one attempt of ``job`` in a fresh staging folder; returns {"staging": path, "info": dict}.

    Runs wherever the executor puts it (this process, a pool worker, a Ray worker); it never
    touches ``job.out_dir`` itself.
    """
    if threads:
        import torch

        torch.set_num_threads(threads)
    staging = job.out_dir.parent / f".staging-{job.out_dir.name}-{uuid.uuid4().hex[:8]}"
    staging.mkdir(parents=True)
    t0 = time.perf_counter()
    try:
        info = resolve(job.fn)(staging, **job.kwargs) or {}
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    info = {**info, "seconds": round(time.perf_counter() - t0, 3), "worker_pid": os.getpid()}
    return {"staging": str(staging), "info": info}


def commit(job: Job, result: dict) -> dict:
    """Driver side: move a finished attempt into place and mark it done (done.json written last)."""
    staging = Path(result["staging"])
    if job.out_dir.exists():  # an unfinished or outdated earlier result
        shutil.rmtree(job.out_dir)
    os.replace(staging, job.out_dir)
    mark_done(job.out_dir, job.key, job=job.name, **result["info"])
    return result["info"]


def clean_staging(jobs: list[Job]) -> None:
    """Remove staging folders left by attempts that died (killed workers, Ctrl-C, crashes)."""
    for parent in {j.out_dir.parent for j in jobs}:
        if parent.exists():
            for stale in parent.glob(".staging-*"):
                shutil.rmtree(stale, ignore_errors=True)


def run_jobs(
    jobs: list[Job],
    executor: str = "local",
    workers: int = 1,
    ray_address: str | None = None,
    retries: int = 2,
    desc: str = "jobs",
    on_done: Callable[[Job, dict], None] | None = None,
) -> dict[str, dict]:
    """Run every job whose results are missing or outdated; returns {job.name: info} for jobs run now.

    ``executor``: "local" (in this process, in order), "process" (``workers`` processes), or
    "ray" (``ray_address``: "auto", "local" or host:port; tasks retried ``retries`` times when a
    worker dies). Finished jobs (same key) are skipped.
    """
    if executor not in EXECUTORS:
        raise UserError(f"unknown executor {executor!r}; use one of {', '.join(EXECUTORS)}")
    clean_staging(jobs)
    pending = [j for j in jobs if not is_done(j.out_dir, j.key)]
    skipped = len(jobs) - len(pending)
    if skipped:
        print(f"{desc}: {skipped} of {len(jobs)} already done, skipped")
    done: dict[str, dict] = {}
    bar = tqdm(total=len(pending), desc=desc, unit="job", disable=not pending)

    def finish(job: Job, result: dict) -> None:
        done[job.name] = commit(job, result)
        if on_done:
            on_done(job, done[job.name])
        bar.update(1)

    try:
        if executor == "local" or (executor == "process" and workers <= 1):
            for job in pending:
                bar.set_postfix_str(job.name)
                finish(job, execute_attempt(job))
        elif executor == "process":
            _run_pool(pending, workers, retries, finish)
        else:
            _run_ray(pending, ray_address or "auto", retries, finish)
    finally:
        bar.close()
    clean_staging(jobs)  # attempts of workers that died and were retried
    return done


def _run_pool(pending: list[Job], workers: int, retries: int, finish) -> None:
    import multiprocessing as mp

    threads = max(1, (os.cpu_count() or 1) // workers)
    attempts = {j.name: 0 for j in pending}
    with shared_cores(), ProcessPoolExecutor(workers, mp_context=mp.get_context("spawn")) as pool:
        futures = {pool.submit(execute_attempt, j, threads): j for j in pending}
        while futures:
            finished, _ = wait(futures, return_when=FIRST_COMPLETED)
            for fut in finished:
                job = futures.pop(fut)
                try:
                    result = fut.result()
                except Exception:
                    attempts[job.name] += 1
                    if attempts[job.name] > retries:
                        raise
                    futures[pool.submit(execute_attempt, job, threads)] = job
                    continue
                finish(job, result)


def _run_ray(pending: list[Job], address: str, retries: int, finish) -> None:
    try:
        import ray
    except ImportError:
        raise UserError("the Ray executor needs Ray: pip install 't2bs[ray]'") from None
    if not ray.is_initialized():
        if address == "local":
            ray.init(include_dashboard=False, log_to_driver=False)
        else:
            try:
                ray.init(address=address, log_to_driver=False)
            except ConnectionError as exc:
                raise UserError(f"cannot reach a Ray cluster at {address!r}: {exc}") from None
    # max_retries re-runs a task whose worker process or node died; each attempt stages apart.
    remote = ray.remote(execute_attempt)
    refs = {
        remote.options(num_cpus=j.num_cpus, num_gpus=j.num_gpus, max_retries=retries, retry_exceptions=False).remote(
            j
        ): j
        for j in pending
    }
    while refs:
        ready, _ = ray.wait(list(refs), num_returns=1)
        for ref in ready:
            job = refs.pop(ref)
            finish(job, ray.get(ref))
