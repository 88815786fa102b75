"""The benchmarks' realistic truth (IGRF-14 degree 13 on an SGP4 orbit, the host's iron after the box's
calibration, the box's 3-day-old TLE and its clock 2 s ahead) against the simulator's models: what the
estimators are given differs from the truth by what the box would not know, and no more."""
import math

import numpy as np
import pytest

from bench import accuracy as acc
from bench import inertia as bi
from bench import realistic
from fsw.estimation import rotations as rot


def _body(q, b_eci):
    return np.array([rot.quat_to_dcm(qk).T @ bk for qk, bk in zip(q, b_eci)])


@pytest.mark.parametrize("mode", ["undirected", "orbital"])
def test_igrf_row_pass_is_the_realistic_world(mode):
    rng = np.random.default_rng([2, list(acc.MODES).index(mode)])
    run = acc.simulate(mode, "asymmetric", 1.0, 0.5e-6, rng, record_samples=30, warmup_s=20.0, world="igrf")
    assert run.meta["world"] == "igrf"
    # the samples: the true field + noise + what the box's calibration leaves of the host's iron (≲ 1 µT)
    resid = run.b_T - run.b_true_T
    assert np.max(np.abs(resid)) < 5 * 0.5e-6 + 1.5e-6
    assert np.linalg.norm(resid.mean(axis=0)) > 0.05e-6  # the residual iron is there
    # the box's field (onboard model, old TLE, clock 2 s ahead) seen through the true attitude: within
    # ~1 µT of the true field in the body, not equal to it
    b_box = _body(run.q_true, run.field.b_eci_T(run.t_s))
    d = np.sqrt(np.mean((b_box - run.b_true_T) ** 2))
    assert 0.01e-6 < d < 1.0e-6
    # and the true field is IGRF, not the dipole the dipole rows use: |B| in the LEO range
    assert np.all((np.linalg.norm(run.b_true_T, axis=1) > 15e-6) & (np.linalg.norm(run.b_true_T, axis=1) < 65e-6))


def test_igrf_row_reports_coverage_per_method():
    row = acc.Row("undirected", "near_symmetric", 1.0, 0.5, world="igrf")
    assert row.key.endswith("/igrf") and len(acc.all_rows(acc.WORLDS)) == 2 * len(acc.all_rows())
    res = acc.run_row(row, runs=1, seed=3, record_samples=20, warmup_s=20.0, methods=("boer", "kalman"))
    cov = res["methods"]["kalman"]["coverage_1sigma"]
    assert 0.0 <= cov <= 1.0 and res["meta"][0]["world"] == "igrf"
    assert "| undirected/near_symmetric/dt1/0.5uT/igrf |" in acc.coverage_markdown({"rows": [res]})


def test_inertia_realistic_record():
    """bench.inertia --world realistic: the scenario on the TLE, its samples through the host's iron and
    the box's calibration, the box's field along its old TLE at its clock."""
    tr = bi.truth_record("aist2d", 120.0, world="realistic")
    assert tr.scenario.tle is not None and tr.scenario.box_tle is not None
    b_box = _body(tr.q, np.asarray(tr.b_inertial(tr.t_s)))
    d = np.sqrt(np.mean((b_box - tr.b_T) ** 2))
    assert 0.01e-6 < d < 1.5e-6
    ideal = bi.truth_record("aist2d", 120.0)
    assert np.sqrt(np.mean((ideal.b_T - _body(ideal.q, np.asarray(ideal.b_inertial(ideal.t_s)))) ** 2)) < 0.5e-6


def test_realistic_host_case_has_the_hosts_iron():
    rec = realistic.simulate(realistic.Case("short", duration_s=20.0), seed=1)
    resid = rec.b_T - rec.b_true_T
    # hard iron (8, −10, 5) µT and ~4 % soft iron on a ~45 µT field: ~14 µT off, uncalibrated
    assert 8e-6 < np.linalg.norm(resid.mean(axis=0)) < 20e-6
    assert rec.t_s[0] == pytest.approx(2.0)
    assert math.degrees(float(np.linalg.norm(rec.w_true_radps[0]))) == pytest.approx(10.2, abs=0.5)


def test_score_rows_per_seed_field_and_method(capsys):
    """`bench.realistic --score`: each method's RMS error and 1-σ coverage with the TLE and without an orbit;
    an unknown method is a usage error (exit 2)."""
    case = realistic.Case("short", inertia_kgm2=realistic.CASES["slow_heavy"].inertia_kgm2, rate_dps=1.0,
                          duration_s=60.0, host=False)
    rows = realistic.score(case, seeds=(0,), methods=("boer", "kalman"))
    assert [(r["field"], r["method"]) for r in rows] == [("tle", "boer"), ("tle", "kalman"),
                                                         ("none", "boer"), ("none", "kalman")]
    for r in rows:
        assert 0.0 <= r["coverage_1sigma"] <= 1.0 and 0.0 < r["rms_dps"] < 10.0
    # kalman never uses the field model: the same estimate and σ with the TLE as without
    assert rows[1]["rms_dps"] == rows[3]["rms_dps"] and rows[1]["coverage_1sigma"] == rows[3]["coverage_1sigma"]
    with pytest.raises(SystemExit) as e:
        realistic.main(["slow_heavy", "--score", "--methods", "nope"])
    assert e.value.code == 2 and "unknown nope" in capsys.readouterr().err


def test_igrf_rows_take_the_drift_out_as_the_flown_calibration_does():
    """The box's calibration follows the hard iron's thermal drift (a harmonic of the orbit,
    fsw.estimation.magcal), so the IGRF rows leave only the calibration's residual in the samples; the
    constant calibration (``--host-drift untracked``, rows ``…/igrf-constant-cal``) leaves the drift in."""
    assert acc.Row("bdot", "asymmetric", 3.0, 0.5, world="igrf").drift_tracked
    assert acc.Row("bdot", "asymmetric", 3.0, 0.5, "igrf", False).key.endswith("/igrf-constant-cal")
    assert all(r.drift_tracked for r in acc.all_rows(acc.WORLDS))
    rms = {}
    for tracked in (True, False):
        run = acc.simulate("undirected", "asymmetric", 3.0, 0.0, np.random.default_rng(5), world="igrf",
                           drift_tracked=tracked, record_samples=400, warmup_s=300.0)
        rms[tracked] = np.sqrt(np.mean((run.b_T - run.b_true_T) ** 2, axis=0))
    # tracked: the 0.15 µT residual (soft-iron residual on ~40 µT: ~0.1 µT) and the chip's 0.04 µT
    assert np.all(rms[True] < 0.35e-6)
    # the scenario's drift (0.6, −0.5, 0.6 µT) is in the constant calibration's samples
    assert np.max(rms[False] - rms[True]) > 0.3e-6


def test_igrf_exact_world_gives_the_box_the_truth():
    """``--world igrf_exact``: the IGRF rows' truth and motions, the box's field the truth itself and no host
    in the samples (what the world's geometry costs, apart from the box's knowledge)."""
    real = acc.simulate("undirected", "asymmetric", 1.0, 0.0, np.random.default_rng(9), world="igrf",
                        record_samples=30, warmup_s=30.0)
    exact = acc.simulate("undirected", "asymmetric", 1.0, 0.0, np.random.default_rng(9), world=acc.IGRF_EXACT,
                         record_samples=30, warmup_s=30.0)
    assert acc.Row("orbital", "asymmetric", 1.0, 0.5, acc.IGRF_EXACT).key.endswith("/igrf-exact")
    np.testing.assert_array_equal(real.w_true_radps, exact.w_true_radps)   # the same motion and truth
    np.testing.assert_allclose(real.b_true_T, exact.b_true_T, atol=1e-15)
    b_box = _body(exact.q_true, exact.field.b_eci_T(exact.t_s))
    assert np.max(np.abs(b_box - exact.b_true_T)) < 1e-12                 # the box's field is the truth
    # the samples hold the chip's noise and quantisation only (0.04 µT, 6 nT steps): no host residual
    assert np.sqrt(np.mean((exact.b_T - exact.b_true_T) ** 2)) < 0.06e-6
    assert np.sqrt(np.mean((real.b_T - real.b_true_T) ** 2)) > 0.08e-6
