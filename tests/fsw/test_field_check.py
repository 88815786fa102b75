"""A recording's field magnitude (fsw.estimation.field_check): refused when it cannot be µT (zero, nT,
gauss, tesla) by every tool with a one-line error naming the file; warned when it is not the Earth's or
not the orbit's model's; the lab recordings pass."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fsw.estimation import field_check as fc
from fsw.estimation.onboard_field import field_from_metadata
from ground import estimate as ge
from ground import inertia as gi
from ground.recording import Recording, write_recording
from support import SHARED_DATA

DATA = SHARED_DATA
B_I_T = np.array([20e-6, -15e-6, 35e-6])          # 43 µT
W = np.radians([6.0, -5.0, 6.5])
#: µT in the file → what a file in other units holds (zero: a dead sensor)
UNITS = {"zero": 0.0, "nT": 1e3, "gauss": 1e-2, "tesla": 1e-6}
HINT = {"zero": "no field at all", "nT": "look like nT", "gauss": "tesla or gauss", "tesla": "tesla or gauss"}


def tumble(n=40, scale=1.0, metadata=None):
    rng = np.random.default_rng(0)
    t = np.arange(n) * 1.0
    b = Rotation.from_rotvec(-np.outer(t, W)).apply(B_I_T) + rng.normal(scale=0.3e-6, size=(n, 3))
    return Recording(t, b * scale, w_ref_radps=np.tile(W, (n, 1)), metadata=metadata or {})


@pytest.mark.parametrize("units", sorted(UNITS))
def test_a_field_that_cannot_be_microtesla_is_refused(units):
    rec = tumble(scale=UNITS[units])
    with pytest.raises(fc.FieldMagnitudeError) as e:
        fc.check(rec.b_T, "run.csv", t_s=rec.t_s)
    text = str(e.value)
    assert text.startswith("run.csv: median |B| is ") and "5–800 µT" in text and HINT[units] in text
    assert "\n" not in text


def test_microtesla_passes_and_milligauss_is_warned():
    assert fc.check(tumble().b_T, "run.csv") == []
    w = fc.check(tumble(scale=10.0).b_T, "run.csv")               # 430 "µT": milligauss, or a magnet
    assert len(w) == 1 and "milligauss" in w[0] and "430 µT" in w[0]


@pytest.mark.parametrize("name", ["broad_02_undisturbed_slow_rotation_B.csv",
                                  "broad_09_undisturbed_fast_rotation_with_breaks_B.csv",
                                  "broad_30_disturbed_stationary_magnet_C.csv", "xio_fusion_sensor_data.csv"])
def test_the_lab_recordings_pass_without_a_warning(name):
    from ground.recording import read_recording
    if not (DATA / name).exists():
        pytest.skip("no lab recordings here")
    rec = read_recording(DATA / name)
    assert fc.check_recording(rec.b_T, name, rec.t_s, rec.metadata) == []
    assert 43.0 < fc.median_uT(rec.b_T) < 45.0


TLE1 = "1 25544U 98067A   26325.50000000  .00016717  00000-0  10270-3 0  9000"
TLE2 = "2 25544  51.6400 208.9163 0006317  69.9862  25.2906 15.50000000    09"
ORBIT = {"orbit_altitude_km": "485", "orbit_inclination_deg": "97.5", "orbit_raan_deg": "30",
         "orbit_arg_lat0_deg": "10", "field_epoch_year": "2026"}


def test_the_orbit_model_from_metadata_is_the_ground_tools_field():
    f = field_from_metadata(ORBIT)
    g, _, _ = gi.field_model(None, ORBIT)                      # hil's model, as ground.inertia uses it
    t = np.linspace(0.0, 6000.0, 7)
    np.testing.assert_allclose(f(t), g(t), rtol=1e-9, atol=1e-15)
    assert field_from_metadata({"source": "lab"}) is None
    # a TLE: the same model as ground.estimate --tle L1 L2 --utc0 ISO
    from types import SimpleNamespace
    tle = SimpleNamespace(scenario=None, tle=(TLE1, TLE2), utc0="2026-11-21T12:00:00")
    f = field_from_metadata({"tle_line1": TLE1, "tle_line2": TLE2, "utc0": tle.utc0})
    np.testing.assert_allclose(f(t), ge.field_from_args(tle)(t), rtol=1e-12)
    assert 18.0 < fc.median_uT(f(t)) < 65.0
    with pytest.raises(ValueError, match="utc0"):
        field_from_metadata({"tle_line1": "1 x", "tle_line2": "2 x"})


def test_a_field_far_from_the_orbits_model_is_warned():
    f = field_from_metadata(ORBIT)
    t = np.arange(0.0, 600.0, 5.0)
    rot = Rotation.from_rotvec(np.outer(t, W))
    b = rot.apply(f(t), inverse=True)                           # the model's field in a tumbling body
    assert fc.check_recording(b, "orbit.csv", t, ORBIT) == []
    w = fc.check_recording(2.0 * b, "orbit.csv", t, ORBIT)
    assert len(w) == 1 and "× the field model's" in w[0] and "along the orbit" in w[0]
    w = fc.check_recording(b, "orbit.csv", t, {**ORBIT, "orbit_altitude_km": "x"})
    assert len(w) == 1 and "orbit metadata not usable" in w[0]


@pytest.mark.parametrize("method", ge.METHODS)
@pytest.mark.parametrize("units", ["zero", "nT", "gauss"])
def test_every_method_refuses_a_field_in_the_wrong_units(tmp_path, capsys, method, units):
    """Zero field: ω = 0 with σ = 0 (Boer, derivative, batch fit) or a confident prior, exit 0; nT and
    gauss: rates that look right with a σ that means nothing. Now: exit 1, one line naming the file,
    nothing written — even with a σ_B given."""
    path = tmp_path / f"{units}.csv"
    write_recording(path, tumble(scale=UNITS[units]))
    out = tmp_path / "rates.csv"
    assert ge.main([str(path), "--rates", str(out), "--method", method, "--sigma-uT", "0.3"]) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"ground.estimate: {path}: median |B| is ") and HINT[units] in err
    assert len(err.splitlines()) == 1 and not out.exists()


def test_milligauss_is_estimated_with_a_warning(tmp_path, capsys):
    path = tmp_path / "mg.csv"
    write_recording(path, tumble(scale=10.0))
    assert ge.main([str(path), "--rates", str(tmp_path / "r.csv"), "--method", "boer"]) == 0
    assert "warning" in capsys.readouterr().err and (tmp_path / "r.csv").exists()


def test_inertia_and_replay_refuse_it_too(tmp_path, capsys):
    from ground.replay import RecordingReplay
    path = tmp_path / "nT.csv"
    for metadata in (ORBIT, {}):                      # the units are named before a missing orbit
        write_recording(path, tumble(scale=1e3, metadata=metadata))
        assert gi.main([str(path), str(tmp_path / "i.json"), "--quiet"]) == 1
        err = capsys.readouterr().err
        assert err.startswith(f"ground.inertia: {path}: median |B|") and "nT" in err
        assert not (tmp_path / "i.json").exists()
    with pytest.raises(fc.FieldMagnitudeError, match="look like nT"):
        RecordingReplay.from_csv(path)
    seen = []
    write_recording(path, tumble(scale=10.0))
    RecordingReplay.from_csv(path, warn=seen.append)
    assert len(seen) == 1 and "milligauss" in seen[0]
