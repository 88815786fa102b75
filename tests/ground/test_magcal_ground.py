"""The ground tools take a host-magnetics calibration (--magcal FILE.json) or estimate it from the
recording along its orbit (--estimate-magcal), and fit the corrected samples."""
import json

import numpy as np
import pytest

from fsw.estimation import magcal as mc
from fsw.estimation import rate_formulas as rf
from ground import estimate as ge
from ground import inertia as gi
from ground.recording import Recording, read_rate_estimates, write_recording
from support import MAGCAL_EPOCH, exit_status, MAGCAL_ORBIT, magcal_host, magcal_orbit, magcal_tumble

SIGMA_T = 1.0e-6
ORBIT_MD = {"orbit_altitude_km": str(MAGCAL_ORBIT[0] / 1e3), "orbit_inclination_deg": str(MAGCAL_ORBIT[1]),
            "orbit_raan_deg": "0", "orbit_arg_lat0_deg": "0", "field_epoch_year": str(MAGCAL_EPOCH)}


@pytest.fixture(scope="module")
def host_record(tmp_path_factory):
    """One orbit of a tumble at 1 Hz seen through a host's iron, with the orbit in the metadata."""
    t, _, _ = magcal_orbit()
    S, h = magcal_host(33)
    truth = magcal_tumble(0)
    noise = np.random.default_rng(4).normal(0.0, SIGMA_T, truth.shape)
    path = tmp_path_factory.mktemp("magcal") / "host.csv"
    write_recording(path, Recording(t, truth @ S.T + h + noise, metadata=dict(ORBIT_MD)))
    return path, t, truth, noise, S, h


def test_a_calibration_file_is_applied_before_the_fit(host_record, tmp_path, capsys):
    path, t, truth, noise, S, h = host_record
    cal = tmp_path / "cal.json"
    cal.write_text(json.dumps(mc.Calibration(h, np.linalg.inv(S) - np.eye(3)).to_json()))
    out = tmp_path / "rates.csv"
    assert ge.main([str(path), "--rates", str(out), "--method", "boer", "--sigma-uT", "1", "--magcal", str(cal)]) == 0
    est = read_rate_estimates(out)
    # Boer on the corrected samples = Boer on the true field plus the noise as the calibration scales it
    expected = rf.boer_rate(t, truth + noise @ np.linalg.inv(S).T)
    np.testing.assert_allclose(est.w_radps[1:], expected[1:], rtol=1e-4, atol=1e-7)
    assert "magcal" in est.metadata and "hard iron" in capsys.readouterr().out


def test_estimate_magcal_recovers_the_host_from_the_recordings_orbit(host_record, tmp_path, capsys):
    path, t, truth, noise, S, h = host_record
    out = tmp_path / "rates.csv"
    assert ge.main([str(path), "--rates", str(out), "--method", "boer", "--sigma-uT", "1",
                    "--estimate-magcal"]) == 0
    line = next(ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("host-magnetics"))
    b_uT = [float(v) for v in line.split("hard iron ")[1].split(" µT")[0].split(", ")]
    assert np.allclose(b_uT, h * 1e6, atol=0.3)   # σ ≈ 0.03 µT at 1 µT noise over an orbit
    est = read_rate_estimates(out)
    uncalibrated = rf.boer_rate(t, truth @ S.T + h + noise)
    ideal = rf.boer_rate(t, truth + noise)
    err = np.nanmean(np.linalg.norm(est.w_radps - ideal, axis=1))
    assert err < 0.1 * np.nanmean(np.linalg.norm(uncalibrated - ideal, axis=1))


def test_estimate_magcal_needs_an_orbit_and_a_bad_file_is_one_line(host_record, tmp_path, capsys):
    path, t, *_ = host_record
    rec = tmp_path / "no_orbit.csv"
    write_recording(rec, Recording(t[:100], np.tile([20e-6, 0, 30e-6], (100, 1)), metadata={}))
    assert ge.main([str(rec), "--rates", str(tmp_path / "r.csv"), "--method", "boer", "--estimate-magcal"]) == 1
    assert "needs the recording's orbit" in capsys.readouterr().err
    bad = tmp_path / "bad.json"
    bad.write_text('{"hard_iron_uT": [1, 2]}')
    assert ge.main([str(path), "--rates", str(tmp_path / "r.csv"), "--method", "boer", "--magcal", str(bad)]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--magcal" in err and "hard_iron_uT" in err
    argv = [str(path), "--rates", str(tmp_path / "r.csv"), "--magcal", str(bad), "--estimate-magcal"]
    assert exit_status(ge.main, argv) == 2


def test_one_direction_is_refused_not_applied(tmp_path, capsys):
    t, b_eci, _ = magcal_orbit()
    S, h = magcal_host(5)
    b = (np.linalg.norm(b_eci, axis=1)[:, None] * np.array([0.6, 0.0, 0.8])) @ S.T + h
    rec = tmp_path / "still.csv"
    write_recording(rec, Recording(t, b, metadata=dict(ORBIT_MD)))
    assert ge.main([str(rec), "--rates", str(tmp_path / "r.csv"), "--method", "boer", "--estimate-magcal"]) == 1
    assert "no calibration from this recording" in capsys.readouterr().err
    assert not (tmp_path / "r.csv").exists()


def test_ground_inertia_takes_the_calibration_before_fitting(host_record, tmp_path, monkeypatch):
    """ground.inertia hands the fit the corrected samples (the fit itself stubbed: its own tests cover it)."""
    path, t, truth, noise, S, h = host_record
    cal = tmp_path / "cal.json"
    cal.write_text(json.dumps(mc.Calibration(h, np.linalg.inv(S) - np.eye(3)).to_json()))
    seen = {}


    def fake_run(rec, b_inertial, **kw):
        seen["b"] = rec.b_T
        raise ValueError("stubbed fit")

    monkeypatch.setattr(gi, "run", fake_run)
    assert gi.main([str(path), str(tmp_path / "i.json"), "--magcal", str(cal), "--quiet"]) == 1
    np.testing.assert_allclose(seen["b"], truth + noise @ np.linalg.inv(S).T, atol=1e-12)


def test_a_calibration_that_is_a_fifo_is_refused_not_waited_on(host_record, tmp_path, capsys):
    """Found by the argument fuzz: --magcal on a FIFO waited for a writer for ever."""
    import os

    path, *_ = host_record
    fifo = tmp_path / "cal.fifo"
    os.mkfifo(fifo)
    assert gi.main([str(path), str(tmp_path / "i.json"), "--magcal", str(fifo), "--quiet"]) == 1
    assert "not a regular file" in capsys.readouterr().err


def test_the_applied_calibrations_hard_iron_sigma_goes_to_the_batch_fit():
    """ground.estimate hands the batch fit the applied calibration's hard-iron 1-σ (the box's, from the
    recording's metadata; an estimated one's own): what is left of the hard iron is fitted as an offset."""
    from argparse import Namespace
    from ground import magcal as gm
    t = np.arange(5.0)
    md = {"magcal_hard_iron_uT": "1, 2, 3", "magcal_soft_iron": "0, 0, 0, 0, 0, 0, 0, 0, 0",
          "magcal_hard_iron_sigma_uT": "0.1, 0.2, 0.15"}
    rec = Recording(t, np.full((5, 3), 30e-6), metadata=md)
    args = Namespace(magcal=None, estimate_magcal=False, no_magcal=False)
    out, how, sigma = gm.calibrate_with_sigma(rec, args, None, 1e-6)
    np.testing.assert_allclose(out.b_T, np.tile(30e-6 - np.array([1e-6, 2e-6, 3e-6]), (5, 1)))
    np.testing.assert_allclose(sigma, [0.1e-6, 0.2e-6, 0.15e-6])
    # NaN (before any calibration), missing or malformed: no σ, so no offset is fitted
    for bad in ("nan, nan, nan", "0.1, 0.2", "a, b, c", "0, 0.1, 0.1"):
        rec = Recording(t, np.full((5, 3), 30e-6), metadata=dict(md, magcal_hard_iron_sigma_uT=bad))
        assert gm.calibrate_with_sigma(rec, args, None, 1e-6)[2] is None
    assert gm.calibrate_with_sigma(rec, Namespace(magcal=None, estimate_magcal=False, no_magcal=True), None,
                                   1e-6)[2] is None
