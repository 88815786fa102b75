"""The ground tools take the orbit (TLE + utc0) and the box's calibration from the recording's metadata by
default, say which they used, and the command line overrides; without an orbit the methods that would use
it say so and widen their σ."""
import json
from datetime import datetime, timezone

import numpy as np
import pytest

from fsw.estimation import magcal as mc
from fsw.estimation import rate_formulas as rf
from ground import estimate as ge
from ground import magcal as gm
from ground.field import LEO_FIELD_TURN_DPS, recording_field, tle_field
from ground.recording import Recording, read_rate_estimates, write_recording
from support import circular_tle, magcal_host, magcal_orbit, magcal_tumble

L1, L2 = circular_tle(epoch="25182.50000000")
UTC0 = "2025-07-01T12:00:00.000000Z"


def box_metadata(h_T, D):
    """What ground.decode writes of the box's knowledge (`ground.box_knowledge`)."""
    return {"utc0": UTC0, "tle_line1": L1, "tle_line2": L2, "tle_state": "ok", "field_model": "igrf14:8",
            "magcal_hard_iron_uT": ", ".join(f"{v * 1e6:.9g}" for v in h_T),
            "magcal_soft_iron": ", ".join(f"{v:.9g}" for v in np.ravel(D)),
            "magcal_hard_iron_sigma_uT": "0.03, 0.03, 0.03", "magcal_state": "converged", "magcal_t_s": "5400.0"}


@pytest.fixture(scope="module")
def host_record(tmp_path_factory):
    t, _, _ = magcal_orbit()
    S, h = magcal_host(33)
    truth = magcal_tumble(0)[:600]
    t = t[:600]
    noise = np.random.default_rng(4).normal(0.0, 1e-6, truth.shape)
    D = np.linalg.inv(S) - np.eye(3)
    path = tmp_path_factory.mktemp("meta") / "box.csv"
    write_recording(path, Recording(t, truth @ S.T + h + noise, metadata=box_metadata(h, D)))
    return path, t, truth, noise, S, h, D


def test_the_box_s_calibration_in_the_metadata_is_applied_by_default_and_said(host_record, tmp_path, capsys):
    path, t, truth, noise, S, h, D = host_record
    out = tmp_path / "r.csv"
    assert ge.main([str(path), "--rates", str(out), "--method", "boer", "--sigma-uT", "1"]) == 0
    text = capsys.readouterr().out
    assert "calibration from the recording's metadata (the box's, converged at t = 5400.0 s" in text
    assert f"field: TLE 99999 from the recording's metadata, t = 0 at {UTC0}" in text
    expected = rf.boer_rate(t, truth + noise @ np.linalg.inv(S).T)      # the truth, the noise as calibrated
    np.testing.assert_allclose(read_rate_estimates(out).w_radps[1:], expected[1:], rtol=1e-4, atol=1e-7)
    # --no-magcal: the samples as they are
    assert ge.main([str(path), "--rates", str(out), "--method", "boer", "--sigma-uT", "1", "--no-magcal"]) == 0
    assert "host-magnetics calibration" not in capsys.readouterr().out
    np.testing.assert_allclose(read_rate_estimates(out).w_radps[1:], rf.boer_rate(t, truth @ S.T + h + noise)[1:],
                               rtol=1e-6, atol=1e-9)
    # a file on the command line wins
    cal = tmp_path / "cal.json"
    cal.write_text(json.dumps(mc.Calibration(np.zeros(3), np.zeros((3, 3))).to_json()))
    assert ge.main([str(path), "--rates", str(out), "--method", "boer", "--sigma-uT", "1", "--magcal", str(cal)]) == 0
    assert f"calibration from {cal}" in capsys.readouterr().out


def test_a_calibration_in_the_metadata_that_is_not_one_is_one_line(host_record, tmp_path, capsys):
    path, t, truth, *_ = host_record
    bad = tmp_path / "bad.csv"
    write_recording(bad, Recording(t[:50], truth[:50], metadata={"magcal_hard_iron_uT": "1, 2"}))
    assert ge.main([str(bad), "--rates", str(tmp_path / "r.csv"), "--method", "boer"]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "magcal_hard_iron_uT" in err
    assert gm.from_metadata({"source": "lab"}) is None


def test_the_orbit_comes_from_the_metadata_unless_the_command_line_says_otherwise():
    md = box_metadata(np.zeros(3), np.zeros((3, 3)))
    t = np.array([0.0, 600.0])
    utc0 = datetime(2025, 7, 1, 12, tzinfo=timezone.utc)
    f, how = recording_field(md)
    assert how.startswith("TLE 99999 from the recording's metadata")
    np.testing.assert_allclose(f.b_eci_T(t), tle_field(L1, L2, utc0).b_eci_T(t), rtol=1e-12)
    later = datetime(2025, 7, 1, 12, 30, tzinfo=timezone.utc)
    f2, how2 = recording_field(md, utc0=later)                # --utc0 alone: the recording's TLE, another t = 0
    assert "(--utc0)" in how2
    np.testing.assert_allclose(f2.b_eci_T(t), tle_field(L1, L2, later).b_eci_T(t), rtol=1e-12)
    other = circular_tle(altitude_km=800.0, epoch="25182.50000000")
    f3, how3 = recording_field(md, tle=other, utc0=utc0)      # --tle --utc0
    assert "of --tle" in how3
    assert not np.allclose(f3.b_eci_T(t), f.b_eci_T(t), rtol=1e-3)
    f4, how4 = recording_field(md, scenario="isoi")
    assert how4.startswith("orbit of scenario isoi")
    assert recording_field({"source": "lab"})[0] is None
    with pytest.raises(ValueError, match="needs the recording's TLE"):
        recording_field({"source": "lab"}, utc0=utc0)


def test_without_an_orbit_the_methods_that_would_use_it_widen_their_sigma(host_record, tmp_path, capsys):
    path, t, truth, *_ = host_record
    lab = tmp_path / "lab.csv"
    write_recording(lab, Recording(t[:50], truth[:50], metadata={"source": "lab"}))
    out = tmp_path / "r.csv"
    assert ge.main([str(lab), "--rates", str(out), "--method", "smoother", "--sigma-uT", "1"]) == 0
    text = capsys.readouterr().out
    assert "field: no orbit" in text and "fixed in inertial space" in text and "sigma_widened" in text
    est = read_rate_estimates(out)
    assert est.metadata["field"] == "fixed in inertial space" and est.metadata["orbit"].startswith("no orbit")
    assert ge.main([str(lab), "--rates", str(out), "--method", "smoother", "--sigma-uT", "1",
                    "--field-turn-dps", "0"]) == 0
    narrow = read_rate_estimates(out).sigma_radps
    # the field's unseen turn, perpendicular to B: (turn²/2)(1 − b̂ᵢ²) added per axis
    bh = truth[:50] / np.linalg.norm(truth[:50], axis=1, keepdims=True)
    turn = np.radians(LEO_FIELD_TURN_DPS)
    np.testing.assert_allclose(est.sigma_radps, np.sqrt(narrow ** 2 + 0.5 * turn ** 2 * (1 - bh ** 2)), rtol=1e-6)
    assert ge.main([str(lab), "--rates", str(out), "--method", "boer", "--sigma-uT", "1"]) == 0
    assert "sigma_widened" in capsys.readouterr().out  # Boer too measures the rate against the field's frame
