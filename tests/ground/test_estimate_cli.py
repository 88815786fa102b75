"""`python -m ground.estimate`: recording in, rate estimates out (one row per sample), plot, errors."""
import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from ground import estimate as ge
from ground.recording import Recording, read_rate_estimates, write_recording

B_I_T = np.array([20e-6, -15e-6, 35e-6])
W = np.radians([6.0, -5.0, 6.5])


@pytest.fixture
def recording(tmp_path):
    rng = np.random.default_rng(0)
    t = np.arange(60) * 1.0
    b = Rotation.from_rotvec(-np.outer(t, W)).apply(B_I_T) + rng.normal(scale=0.2e-6, size=(60, 3))
    path = tmp_path / "run.csv"
    write_recording(path, Recording(t, b, w_ref_radps=np.tile(W, (60, 1)), metadata={"source": "test"}))
    return path


@pytest.mark.parametrize("method", ["boer", "derivative", "kotelnikov", "kalman", "smoother"])
def test_every_method_writes_one_row_per_sample(recording, tmp_path, method, capsys):
    out = tmp_path / f"{method}.csv"
    assert ge.main([str(recording), "--rates", str(out), "--method", method, "--sigma-uT", "0.2"]) == 0
    est = read_rate_estimates(out)
    assert len(est) == 60
    np.testing.assert_array_equal(est.t_s, np.arange(60) * 1.0)
    assert est.metadata["method"] == method
    first_valid = {"boer": 1, "derivative": 2}.get(method, 1)
    assert np.all(np.isnan(est.w_radps[:first_valid])) or method not in ("boer", "derivative")
    assert np.all(np.isfinite(est.w_radps[10:50]))
    text = capsys.readouterr().out
    assert "error vs reference" in text


def test_full_vector_methods_are_scored_against_the_reference(recording, tmp_path, capsys):
    out = tmp_path / "k.csv"
    ge.main([str(recording), "--rates", str(out), "--method", "smoother", "--sigma-uT", "0.2"])
    est = read_rate_estimates(out)
    assert np.sqrt(np.mean(np.sum((est.w_radps[5:] - W) ** 2, axis=1))) < math.radians(0.2)
    assert "full RMS" in capsys.readouterr().out


def test_plot_and_decimation(recording, tmp_path):
    out, png = tmp_path / "r.csv", tmp_path / "r.png"
    assert ge.main([str(recording), "--rates", str(out), "--method", "boer", "--plot", str(png),
                    "--decimate-hz", "0.5"]) == 0
    assert png.stat().st_size > 1000
    assert len(read_rate_estimates(out)) == 30


@pytest.mark.parametrize("method", ["kalman-orbit", "kalman-mm"])
def test_scenario_orbit_option(recording, tmp_path, capsys, method):
    out = tmp_path / "o.csv"
    assert ge.main([str(recording), "--rates", str(out), "--method", method, "--scenario", "isoi",
                    "--sigma-uT", "0.2"]) == 0
    est = read_rate_estimates(out)
    assert est.metadata["field"] == "along the orbit" and len(est) > 0


def test_bad_input_is_an_error_naming_the_file(tmp_path, capsys):
    bad = tmp_path / "bad.csv"
    bad.write_text("t_s,bx_uT,by_uT,bz_uT\n0,1,2,3\n0,1,2,3\n")
    assert ge.main([str(bad), "--rates", str(tmp_path / "o.csv")]) == 1
    assert "bad.csv" in capsys.readouterr().err
    assert not (tmp_path / "o.csv").exists()


def test_noise_estimate_from_third_differences():
    rng = np.random.default_rng(2)
    t = np.arange(5000) * 0.01
    b = Rotation.from_rotvec(-np.outer(t, W)).apply(B_I_T) + rng.normal(scale=0.3e-6, size=(5000, 3))
    assert ge.noise_estimate_T(b) == pytest.approx(0.3e-6, rel=0.1)
