"""python -m bench.campaign scaling: what the runner costs and how a campaign scales here.

- the embedded cluster's start (one and two workers);
- an empty task's round trip, one at a time (submit → result) and many at once (tasks per second);
- the same campaign file on one worker and on two (both on a local cluster, so that the ratio is the
  workers' alone), the speed-up, and each run's result size (the JSON payload and the Parquet file per run);
- the load average before and after: the machine may be shared, and a ratio measured while others run is
  what it is.
"""
from __future__ import annotations

import json
import os
import tempfile
import time
from pathlib import Path

from bench.campaign import campaign_file as cf
from bench.campaign import results as rs
from bench.campaign.runner import execute, local_cluster, run_campaign
from bench.campaign.runs import Run
from bench.campaign.scenarios import SCENARIOS


def _empty(run: Run) -> dict:
    return {}


def overhead(tasks: int = 200, sequential: int = 30) -> dict:
    """An empty task's cost on a local cluster of two workers."""
    from distributed import Client
    t0 = time.perf_counter()
    with local_cluster(2) as cluster, Client(cluster) as c:
        start_s = time.perf_counter() - t0
        c.submit(execute, _empty, Run("warm", (0,)), pure=False).result()
        t0 = time.perf_counter()
        for i in range(sequential):
            c.submit(execute, _empty, Run(f"s{i}", (i,)), pure=False).result()
        round_trip_s = (time.perf_counter() - t0) / sequential
        t0 = time.perf_counter()
        futs = [c.submit(execute, _empty, Run(f"b{i}", (i,)), pure=False) for i in range(tasks)]
        c.gather(futs)
        per_task_s = (time.perf_counter() - t0) / tasks
    return {"cluster_start_s": start_s, "round_trip_s": round_trip_s, "throughput_per_task_s": per_task_s,
            "tasks": tasks}


def scaling(path, runs: int | None = None) -> dict:
    """The campaign file at `path` (its first `runs` runs) on one worker and on two."""
    camp = cf.load(path)
    specs = camp.run_specs()[:runs] if runs else camp.run_specs()
    fn = SCENARIOS[camp.scenario].task
    out = {"campaign": camp.name, "runs": len(specs)}
    results = {}
    with tempfile.TemporaryDirectory() as tmp:
        for workers in (1, 2):
            f = Path(tmp) / f"w{workers}.parquet"
            t0 = time.perf_counter()
            results[workers] = run_campaign(fn, specs, config=camp.config(), name=f"{workers} worker(s)",
                                            workers=workers, in_process=False, results=f, progress=False)
            out[f"wall_s_{workers}_workers"] = time.perf_counter() - t0
            out["parquet_bytes_per_run"] = f.stat().st_size / len(specs)
            table = rs.read(f)[1]
            out[f"run_cpu_s_mean_{workers}_workers"] = float(sum(table.column("cpu_s").to_pylist()) / len(specs))
            out[f"run_wall_s_mean_{workers}_workers"] = float(sum(table.column("elapsed_s").to_pylist()) / len(specs))
    out["speed_up"] = out["wall_s_1_workers"] / out["wall_s_2_workers"]
    out["identical"] = all(rs.encode(a) == rs.encode(b) for a, b in zip(results[1], results[2]))
    out["result_bytes_per_run"] = sum(len(rs.encode(r)) for r in results[1]) / len(specs)
    return out


def main(path, runs: int | None = None, tasks: int = 200) -> dict:
    load0 = os.getloadavg()
    res = {"cores": os.cpu_count(), "load_before": load0, "overhead": overhead(tasks), "scaling": scaling(path, runs)}
    res["load_after"] = os.getloadavg()
    print(json.dumps(res, indent=1))
    return res
