"""The runs of a campaign as tasks on dask.distributed.

By default an embedded local cluster, one single-threaded worker process per core (no set-up, no dashboard,
quiet logs, on free ports); with a scheduler's address the runs go to that cluster instead. One worker and no
address: the runs in this process, one after the other (the same results, without starting a cluster).

Every run is a task of its own. Results are stored as each completes (:mod:`bench.campaign.results`); a run
already in the results file is not run again. A worker that dies mid-run (killed, out of memory, its
machine gone) loses only its runs in progress: the scheduler gives them to another worker (up to
``distributed.scheduler.allowed-failures`` deaths a run); a run that raises is retried `retries` times. Since a
run's seed is its own (:mod:`bench.campaign.runs`), a retried run, or one run on another worker, gives the same
result bit for bit.
"""
from __future__ import annotations

import contextlib
import logging
import os
import sys
import time
import uuid
from collections.abc import Callable, Iterator

from bench.campaign import results as rs
from bench.campaign.runs import Run


class CampaignError(Exception):
    """A campaign that cannot run or complete (one line, for the user)."""


def default_workers() -> int:
    """One worker per core this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def execute(fn: Callable, run: Run) -> dict:
    """Run `run` (on a worker, or here); its results-file row."""
    t0, c0 = time.perf_counter(), time.thread_time()
    result = fn(run)
    elapsed, cpu = time.perf_counter() - t0, time.thread_time() - c0
    try:
        from distributed import get_worker
        worker = get_worker().address
    except (ImportError, ValueError):
        worker = "local"
    return rs.row(run, result, elapsed_s=elapsed, cpu_s=cpu, worker=worker)


@contextlib.contextmanager
def client(workers: int | None = None, scheduler: str | None = None) -> Iterator:
    """A dask.distributed Client: on the cluster at `scheduler`, else on a local cluster of `workers`
    processes (default: one per core) that ends with the block."""
    from distributed import Client
    if scheduler:
        try:
            c = Client(scheduler, timeout="20s")
        except (OSError, TimeoutError) as e:
            raise CampaignError(f"--scheduler {scheduler}: cannot connect ({e})") from None
        with c:
            yield c
        return
    with local_cluster(workers or default_workers()) as cluster, Client(cluster) as c:
        yield c


def local_cluster(workers: int):
    """An embedded cluster of `workers` single-threaded processes on free ports of this host: no dashboard (its
    HTTP endpoint on a free port, so that two clusters do not contend for 8787), only errors logged."""
    from distributed import LocalCluster
    return LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, host="127.0.0.1", scheduler_port=0,
                        dashboard_address=None, worker_dashboard_address=None, silence_logs=logging.ERROR,
                        scheduler_kwargs={"dashboard_address": "127.0.0.1:0"})


def _progress(total: int, done: int, name: str, show: bool):
    from tqdm import tqdm
    return tqdm(total=total, initial=done, desc=name, unit="run", disable=not show, file=sys.stderr,
                dynamic_ncols=True)


def run_campaign(fn: Callable, runs: list[Run], *, config: dict, name: str = "campaign", workers: int | None = None,
                 scheduler: str | None = None, results=None, progress: bool = True, retries: int = 2,
                 in_process: bool | None = None, on_result: Callable[[Run, dict], None] | None = None,
                 elapsed_s: dict | None = None) -> list:
    """Every run of `runs` through `fn(run) -> result`; the results, in the order of `runs`.

    `fn` must be picklable (a module-level function, or functools.partial of one). `config`: whatever, besides
    the runs' own seeds and parameters, decides the results (stored with them, and checked when a results
    file is continued). `results`: the Parquet file that keeps every run (runs already in it are not run
    again); without it the results live in memory only. `in_process`: run here rather than on a cluster
    (default: without a scheduler, when one worker or one run to do). `on_result(run, result)`: called as each
    run completes.
    `elapsed_s`: a dict filled with each run's time in its task (seconds, by id; stored runs: as stored).
    Raises CampaignError when a run fails for good (the others completed and stored)."""
    ids = [r.id for r in runs]
    if len(set(ids)) != len(ids):
        raise CampaignError("two runs of the campaign have the same id")
    store = rs.ResultsFile(results, config) if results is not None else None
    try:
        stored = store.load() if store else {}
        if store:
            store.check(runs, stored)
            store.consolidate(ids)
    except rs.ResultsError as e:
        raise CampaignError(str(e)) from None
    rows = {rid: r for rid, r in stored.items() if rid in set(ids)}
    todo = [r for r in runs if r.id not in rows]
    failures: list[str] = []

    def done(run: Run, row: dict) -> None:
        rows[run.id] = row
        if store:
            store.append(row)
        if on_result is not None:
            on_result(run, rs.decode(row["result"]))

    bar = _progress(len(runs), len(runs) - len(todo), name, progress)
    try:
        if in_process is None:
            in_process = scheduler is None and min(workers or default_workers(), len(todo)) <= 1
        if todo and in_process:
            for run in todo:
                done(run, execute(fn, run))
                bar.update(1)
        elif todo:
            from distributed import as_completed
            with client(workers, scheduler) as c:
                token = uuid.uuid4().hex[:8]
                futures = {c.submit(execute, fn, run, key=f"{name}-{token}-{i}", retries=retries, pure=False): run
                           for i, run in enumerate(todo)}
                for fut in as_completed(futures):
                    run = futures[fut]
                    try:
                        row = fut.result()
                    except Exception as e:  # noqa: BLE001 - the run's own error, reported with its id
                        failures.append(f"run {run.id}: {type(e).__name__}: {e}")
                    else:
                        done(run, row)
                    fut.release()
                    bar.update(1)
    finally:
        bar.close()
        if store:
            store.consolidate(ids)
    if elapsed_s is not None:
        elapsed_s.update({rid: r["elapsed_s"] for rid, r in rows.items()})
    if failures:
        raise CampaignError(f"{len(failures)} run(s) failed ({len(runs) - len(failures)} stored): " + failures[0])
    return [rs.decode(rows[r.id]["result"]) for r in runs]


def rerun(fn: Callable, runs: list[Run], run_id: str, *, config: dict, results) -> tuple[bool, str]:
    """Run `run_id` alone, here, and compare its result with the stored one: (the same?, a line saying so)."""
    by_id = {r.id: r for r in runs}
    if run_id not in by_id:
        shown = ", ".join(list(by_id)[:3]) + (", …" if len(by_id) > 3 else "")
        raise CampaignError(f"--rerun {run_id}: no such run in this campaign (ids: {shown})")
    store = rs.ResultsFile(results, config)
    try:
        stored = store.load()
        store.check([by_id[run_id]], stored)
    except rs.ResultsError as e:
        raise CampaignError(str(e)) from None
    if run_id not in stored:
        raise CampaignError(f"--rerun {run_id}: not in {results} yet (run the campaign first)")
    run = by_id[run_id]
    new = execute(fn, run)
    same = new["result"] == stored[run_id]["result"]
    head = f"run {run_id} (seed {list(run.seed)}, parameters {run.params_json()}): re-run in {new['elapsed_s']:.1f} s"
    if same:
        return True, f"{head}; the result matches the stored row bit for bit"
    old, now = rs.decode(stored[run_id]["result"]), rs.decode(new["result"])
    keys = sorted(k for k in set(old) | set(now) if rs.encode(old.get(k)) != rs.encode(now.get(k))) \
        if isinstance(old, dict) and isinstance(now, dict) else []
    return False, f"{head}; the result DIFFERS from the stored row" + (f" in {', '.join(keys[:10])}" if keys else "")
