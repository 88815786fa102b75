"""The accuracy benchmark (bench.accuracy): the simulated passes against independent truth, and a short
form of the table (one run of two rows) as the CI check of the whole chain."""
import json
import math

import numpy as np
import pytest

from fsw.estimation import rate_formulas as rf
from bench import accuracy as acc
from bench.accuracy_world import BDOT_DISTURB_T


@pytest.mark.parametrize("mode", list(acc.MODES))
def test_simulated_pass_is_consistent(mode):
    rng = np.random.default_rng([1, list(acc.MODES).index(mode)])
    run = acc.simulate(mode, "asymmetric", 1.0, 0.5e-6, rng, record_samples=30, warmup_s=20.0)
    n = len(run.t_s)
    assert run.record == slice(20, 50) and run.b_T.shape == (n, 3)
    # the measured field is the true one plus the stated noise (and, for −Ḃ, the torquers' field)
    resid = run.b_T - run.b_true_T
    limit = 0.5e-6 * 5 + (BDOT_DISTURB_T * math.sqrt(3) if mode == "bdot" else 0.0)
    assert np.max(np.abs(resid)) < limit
    assert 0.2e-6 < np.std(resid) < 0.9e-6
    # |B| is the orbit's: LEO dipole field
    assert np.all((np.linalg.norm(run.b_true_T, axis=1) > 15e-6) & (np.linalg.norm(run.b_true_T, axis=1) < 65e-6))
    rate = np.degrees(np.linalg.norm(run.w_true_radps[run.record], axis=1))
    lo, hi = acc.MODES[mode]
    if mode == "orbital":   # RMS of the libration rate drawn in range
        assert 0.3 * lo < math.sqrt(np.mean(rate ** 2)) < 1.5 * hi
    else:
        assert np.all((rate > 0.7 * lo) & (rate < 1.1 * hi))


def test_truth_rate_is_the_rate_of_the_truth_field():
    """Noise-free check of the truth's conventions: the Boer formula on the true field at a fine step is
    the true perpendicular rate (dB/dt = B × ω plus the field's slow turning)."""
    rng = np.random.default_rng(7)
    run = acc.simulate("undirected", "near_symmetric", 1.0, 0.0, rng, record_samples=20, warmup_s=0.0)
    t, b, w = run.t_s, run.b_true_T, run.w_true_radps
    boer = rf.boer_rate(t, b)
    bh = b / np.linalg.norm(b, axis=1, keepdims=True)
    perp = w - np.sum(w * bh, axis=1, keepdims=True) * bh
    # first-order formula at 1 s: error about |ω|²Δt/2, well below |ω|
    err = np.linalg.norm(boer[1:] - perp[1:], axis=1)
    assert np.max(err) < 0.6 * np.linalg.norm(w, axis=1).max() ** 2 + math.radians(0.3)


def test_bdot_mode_takes_energy_out():
    rng = np.random.default_rng(3)
    run = acc.simulate("bdot", "near_symmetric", 1.0, 0.5e-6, rng, record_samples=10, warmup_s=600.0)
    w = np.linalg.norm(run.w_true_radps, axis=1)
    assert w[-1] < 0.95 * w[0]


def test_orbital_mode_follows_the_orbital_frame():
    """With the libration taken out, the body rate is the orbital frame's: n about the orbit normal."""
    rng = np.random.default_rng(5)
    run = acc.simulate("orbital", "asymmetric", 1.0, 0.0, rng, record_samples=10, warmup_s=0.0)
    assert np.all(np.isfinite(run.w_true_radps))
    assert np.max(np.linalg.norm(run.w_true_radps, axis=1)) < math.radians(3.0 * 3)


@pytest.mark.parametrize("row", [acc.Row("undirected", "near_symmetric", 1.0, 0.5),
                                 acc.Row("undirected", "asymmetric", 3.0, 0.5)])
def test_short_benchmark_rows(row):
    """One short run per row: every method answers, Boer's error is the usual size, the ground smoother
    beats it by far (the benchmark's claim in miniature), the table renders."""
    res = acc.run_row(row, runs=1, seed=11, record_samples=40, warmup_s=60.0)
    m = res["methods"]
    assert set(acc.METHODS) <= set(m)
    assert 0.05 < m["boer"]["perp_rms_dps"] < 20.0
    assert res["best_ground"]["ratio_to_boer_perp"] < 0.5
    assert all(np.isfinite(v["perp_rms_dps"]) for v in m.values())
    table = acc.markdown({"rows": [res]})
    assert table.count("\n") == 2 and row.mode in table


def test_a_method_that_fails_on_a_run_is_counted_and_not_the_best(monkeypatch):
    """A method that gives nothing on one run is listed in `failed_runs` (its pooled errors would
    otherwise come from the runs where it worked) and cannot be the row's best method; non-finite rows
    are counted in `missing_samples`."""
    real = acc.estimate
    calls = []

    def flaky(run, sigma_b_T, methods=acc.METHODS):
        est = real(run, sigma_b_T, methods)
        calls.append(len(calls))
        if len(calls) == 1:
            del est["kalman"]
        else:
            est["kalman_orbit"][0][0] = np.nan
        return est
    monkeypatch.setattr(acc, "estimate", flaky)
    res = acc.run_row(acc.Row("undirected", "near_symmetric", 1.0, 0.5), runs=2, seed=3, record_samples=20,
                      warmup_s=20.0, methods=("boer", "kalman", "kalman_orbit"))
    m = res["methods"]
    assert m["kalman"]["failed_runs"] == [0] and m["kalman_orbit"]["failed_runs"] == []
    assert m["kalman_orbit"]["missing_samples"] == 1 and m["kalman"]["missing_samples"] == 0
    assert res["best_onboard"]["method"] == "kalman_orbit"


@pytest.mark.slow
def test_the_runs_on_two_workers_are_the_runs_here(tmp_path):
    """Every run a campaign task (bench.campaign) on a local cluster of two worker processes: the row's pooled
    statistics are those of the runs here, to the bit; the results file holds every run and resumes."""
    row = acc.Row("undirected", "near_symmetric", 1.0, 0.5)
    methods = ("boer", "kalman", "smoother", "euler", "euler_rts", "auto")
    here = acc.run_row(row, runs=3, seed=11, record_samples=20, warmup_s=20.0, methods=methods)
    res = tmp_path / "acc.parquet"
    there = acc.run_benchmark([row], runs=3, seed=11, record_samples=20, warmup_s=20.0, log=lambda s: None,
                              methods=methods, workers=2, results=res)
    assert _text(there["rows"][0]) == _text(here)
    seen = []
    again = acc.run_benchmark([row], runs=4, seed=11, record_samples=20, warmup_s=20.0, log=seen.append,
                              methods=methods, workers=2, results=res)
    assert _text(again["rows"][0]) == _text(acc.run_row(row, runs=4, seed=11, record_samples=20, warmup_s=20.0,
                                                        methods=methods))
    assert len(seen) == 1 and row.key in seen[0]   # the row's line, its runs partly from the file


def _text(res: dict) -> str:
    """A row's statistics as the JSON the benchmark writes (NaN compares equal to NaN there)."""
    return json.dumps(res, default=float, sort_keys=True)
