"""The campaign runner (bench.campaign) on a real local cluster of 2 worker processes: results that do not
depend on the number of workers, a worker killed mid-campaign, resuming, re-running one run."""
import json
import math
import os
import signal
import sys
from pathlib import Path

import cloudpickle
import numpy as np
import pyarrow.parquet as pq
import pytest

from bench.campaign import CampaignError, Run, derive_seed, rerun, run_campaign
from bench.campaign import results as rs
from bench.campaign.runner import local_cluster

# the tasks below run in the workers: sent by value, whatever the workers' import path
cloudpickle.register_pickle_by_value(sys.modules[__name__])

CONFIG = {"test": "campaign"}


def draws(run: Run) -> dict:
    """A run's result from its seed alone: a few draws, an array, a NaN."""
    rng = np.random.default_rng(list(run.seed))
    return {"x": float(rng.normal()) * run.params["scale"], "v": rng.normal(size=(3, 4)), "nan": math.nan,
            "n": int(rng.integers(1000))}


def fail_on_marked(run: Run) -> dict:
    """Raises for the runs listed in the marker file, else draws()."""
    if run.id in Path(run.params["marker"]).read_text().split():
        raise RuntimeError("this run fails")
    return draws(run)


def kill_own_worker_once(run: Run) -> dict:
    """The first run to get here kills its own worker process (SIGKILL: no clean-up, as a lost machine);
    its retry, elsewhere, gives draws()."""
    marker = Path(run.params["marker"])
    if run.id == "r3":
        try:
            fd = os.open(marker, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
        except FileExistsError:
            pass
        else:
            os.close(fd)
            os.kill(os.getpid(), signal.SIGKILL)
    return draws(run)


def _runs(n=8, **params):
    return [Run(f"r{i}", derive_seed(11, f"r{i}"), {"scale": 2.0, **params}) for i in range(n)]


def _same(a, b):
    return rs.encode(a) == rs.encode(b)


@pytest.fixture(scope="module")
def cluster():
    with local_cluster(2) as c:   # the runner's own, on free ports
        yield c


def test_seeds_come_from_the_campaign_and_the_run_id_only():
    assert derive_seed(11, "r1") == derive_seed(11, "r1")
    assert derive_seed(11, "r1") != derive_seed(11, "r2") and derive_seed(11, "r1") != derive_seed(12, "r1")
    # a fixed value: the same on every machine and Python (hash() is not)
    assert derive_seed(0, "a")[1] == int.from_bytes(bytes.fromhex("ca978112"), "little")


def test_the_stored_result_is_exact():
    x = {"a": np.array([[1.0, math.nan], [math.inf, -0.0]]), "b": [1, "s", None, True], "c": 1 / 3,
         "i": np.arange(4, dtype=np.int32)}
    y = rs.decode(rs.encode(x))
    assert y["a"].tobytes() == x["a"].tobytes() and y["i"].dtype == np.int32 and y["c"] == 1 / 3
    assert y["b"] == x["b"]


def test_two_workers_give_what_one_process_gives_and_the_file_resumes(cluster, tmp_path):
    runs = _runs()
    alone = run_campaign(draws, runs, config=CONFIG, workers=1, progress=False)
    out = tmp_path / "out.parquet"
    on_two = run_campaign(draws, runs, config=CONFIG, scheduler=cluster.scheduler_address, results=out,
                          progress=False)
    assert all(_same(a, b) for a, b in zip(alone, on_two))
    table = pq.read_table(out)
    assert table.column("run_id").to_pylist() == [r.id for r in runs]
    assert table.column("p.scale").to_pylist() == [2.0] * 8
    assert json.loads(table.column("seed").to_pylist()[2]) == list(derive_seed(11, "r2"))
    assert np.array_equal(table.column("r.x").to_numpy(), [a["x"] for a in alone])
    assert len(set(table.column("worker").to_pylist())) == 2   # both workers ran some
    # the same campaign again, with more runs: only the new ones run
    seen = []
    more = run_campaign(draws, _runs(10), config=CONFIG, scheduler=cluster.scheduler_address, results=out,
                        progress=False, on_result=lambda run, res: seen.append(run.id))
    assert sorted(seen) == ["r8", "r9"] and all(_same(a, b) for a, b in zip(alone, more))


def test_a_failed_run_keeps_the_others_and_the_restart_runs_only_what_is_missing(cluster, tmp_path):
    marker = tmp_path / "fail"
    marker.write_text("r2 r5")
    out = tmp_path / "out.parquet"
    runs = _runs(marker=str(marker))
    with pytest.raises(CampaignError, match="2 run.s. failed .6 stored.: run r[25]: RuntimeError"):
        run_campaign(fail_on_marked, runs, config=CONFIG, scheduler=cluster.scheduler_address, results=out,
                     progress=False)
    assert sorted(pq.read_table(out).column("run_id").to_pylist()) == ["r0", "r1", "r3", "r4", "r6", "r7"]
    marker.write_text("")
    seen = []
    res = run_campaign(fail_on_marked, runs, config=CONFIG, workers=1, results=out, progress=False,
                       on_result=lambda run, r: seen.append(run.id))
    assert sorted(seen) == ["r2", "r5"]
    assert all(_same(a, b) for a, b in zip(res, run_campaign(draws, runs, config=CONFIG, workers=1, progress=False)))


def test_a_killed_worker_s_run_is_retried_elsewhere_with_the_same_result(cluster, tmp_path):
    marker = tmp_path / "killed"
    runs = _runs(marker=str(marker))
    got = run_campaign(kill_own_worker_once, runs, config=CONFIG, scheduler=cluster.scheduler_address,
                       results=tmp_path / "out.parquet", progress=False)
    assert marker.exists()   # a worker did die
    want = run_campaign(draws, runs, config=CONFIG, workers=1, progress=False)
    assert all(_same(a, b) for a, b in zip(got, want))


def test_rerun_matches_the_stored_row_and_sees_a_changed_one(tmp_path):
    out = tmp_path / "out.parquet"
    runs = _runs(4)
    run_campaign(draws, runs, config=CONFIG, workers=1, results=out, progress=False)
    same, line = rerun(draws, runs, "r2", config=CONFIG, results=out)
    assert same and "r2" in line and "matches" in line
    doubled = [Run(r.id, r.seed, r.params) for r in runs]
    same, line = rerun(lambda run: {**draws(run), "x": 0.0}, doubled, "r2", config=CONFIG, results=out)
    assert not same and "DIFFERS" in line and " x" in line
    with pytest.raises(CampaignError, match="no such run"):
        rerun(draws, runs, "r99", config=CONFIG, results=out)


def test_a_results_file_of_another_campaign_is_refused(tmp_path):
    out = tmp_path / "out.parquet"
    run_campaign(draws, _runs(2), config=CONFIG, workers=1, results=out, progress=False)
    with pytest.raises(CampaignError, match="another campaign"):
        run_campaign(draws, _runs(2), config={"test": "other"}, workers=1, results=out, progress=False)
    other = [Run("r0", derive_seed(12, "r0"), {"scale": 2.0})]
    with pytest.raises(CampaignError, match="run r0 was stored with seed"):
        run_campaign(draws, other, config=CONFIG, workers=1, results=out, progress=False)


def test_the_embedded_local_cluster_runs_a_campaign():
    runs = _runs(4)
    got = run_campaign(draws, runs, config=CONFIG, workers=2, progress=False)
    assert all(_same(a, b) for a, b in zip(got, run_campaign(draws, runs, config=CONFIG, workers=1, progress=False)))


PROBE = """name = "probe-test"
scenario = "probe"
runs = 6
seed = 3
figures = ["x"]
[fixed]
payload_floats = 4
[disperse]
mean = {dist = "uniform", low = 10.0, high = 20.0}
"""


def test_a_campaign_file_runs_resumes_reruns_and_reports(tmp_path, capsys):
    from bench.campaign import campaign_file as cf
    from bench.campaign.__main__ import main
    f = tmp_path / "probe.toml"
    f.write_text(PROBE)
    camp = cf.load(f)
    runs = camp.run_specs()
    assert [r.id for r in runs] == [f"r{i:05d}" for i in range(6)]
    means = [r.params["mean"] for r in runs]
    assert all(10.0 <= m <= 20.0 for m in means) and len(set(means)) == 6
    assert camp.run_specs() == runs                       # the draws are the campaign's, not the moment's
    out = tmp_path / "probe.parquet"
    assert main([str(f), "--workers", "1", "--results", str(out)]) == 0
    text = capsys.readouterr().out
    assert "6 runs of probe" in text and "| x | 6 |" in text
    assert main([str(f), "--results", str(out), "--rerun", "r00004"]) == 0
    assert "matches the stored row bit for bit" in capsys.readouterr().out
    assert main(["report", str(out)]) == 0
    table = capsys.readouterr().out
    xs = pq.read_table(out).column("r.x").to_numpy()
    assert f"| x | 6 | {np.mean(xs):.4g} |" in table      # the report is the file's


@pytest.mark.parametrize("text, says", [
    ('scenario = "nope"\nruns = 1', "scenario must be one of"),
    ('scenario = "probe"\nruns = 0', "runs must be"),
    ('scenario = "probe"\nruns = 1\nbogus = 1', "unknown key(s) bogus"),
    ('scenario = "probe"\nruns = 1\n[disperse]\nmean = {dist = "normal", mean = 0.0}', "normal takes mean, sd"),
    ('scenario = "probe"\nruns = 1\n[disperse]\nmean = {dist = "uniform", low = 2.0, high = 1.0}', "low < high"),
    ('scenario = "probe"\nruns = 1\n[fixed]\nspeed = 3', "has no parameter(s) speed"),
    ('scenario = "probe"\nruns = [', "not TOML"),
])
def test_a_bad_campaign_file_is_a_one_line_usage_error(tmp_path, capsys, text, says):
    from bench.campaign.__main__ import main
    f = tmp_path / "bad.toml"
    f.write_text(text)
    with pytest.raises(SystemExit) as e:
        main([str(f), "--workers", "1"])
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert says in err and "Traceback" not in err
