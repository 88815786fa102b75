"""A recording as the flight software's magnetometer: timing of the replay, the Kalman filter sent on
every sample, and `python -m fsw.main --replay ... --rates-out ...`."""
import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fsw import main as fsw_main
from fsw.flight import FlightSoftware
from ground.replay import RecordingReplay
from fsw.telemetry.dialect import mavlink
from fsw.telemetry.telemetry import Telemetry
from ground.recording import Recording, read_rate_estimates, write_recording
from support import Capture

B_I_T = np.array([20e-6, -15e-6, 35e-6])
W = np.radians([6.0, -5.0, 6.5])


def field(t):
    return Rotation.from_rotvec(-np.outer(t, W)).apply(B_I_T)


def test_replay_delivers_each_sample_once_at_its_time():
    t = np.array([0.0, 0.1, 0.25, 0.3, 0.9])
    src = RecordingReplay(t, field(t))
    got = []
    for k in range(60):
        now = k * 0.02
        if src.update(now):
            got.append((now, src.sample_time_s))
            np.testing.assert_allclose(src.b_body_T, field(np.array([src.sample_time_s]))[0], rtol=1e-12)
    assert [s for _, s in got] == list(t)
    assert all(now >= s - 1e-9 and now - s < 0.02 + 1e-9 for now, s in got)
    assert src.done and src.max_lag_s < 0.02 + 1e-9


def test_a_slow_loop_falls_behind_but_skips_nothing():
    t = np.arange(10) * 0.01
    src = RecordingReplay(t, field(t))
    times = [src.sample_time_s for k in range(20) if src.update(k * 0.05)]
    assert times == list(t) and src.max_lag_s > 0.05


def test_bad_recordings_are_refused():
    with pytest.raises(ValueError):
        RecordingReplay(np.array([0.0, 0.0]), np.zeros((2, 3)))
    with pytest.raises(ValueError):
        RecordingReplay(np.array([0.0, 1.0]), np.zeros((3, 3)))


def test_flight_software_sends_the_kalman_estimate_for_every_sample():
    t = np.arange(40) * 0.5
    link = Capture()
    fsw = FlightSoftware(RecordingReplay(t, field(t)), Telemetry(link), rate_hz=10.0, sigma_b_T=0.1e-6,
                         sample_rate_hz=2.0)
    for k in range(210):
        fsw.tick(k * 0.1)
    est = [m for m in link.messages() if m.get_type() == "DEBRIS_RATE_ESTIMATE"
           and m.method == mavlink.DEBRIS_RATE_METHOD_KALMAN]
    assert len(est) == 40
    assert est[0].flags & mavlink.DEBRIS_ESTIMATE_FLAGS_NO_ESTIMATE
    last = est[-1]
    np.testing.assert_allclose([last.wx, last.wy, last.wz], W, atol=math.radians(0.1))
    assert all(math.isfinite(v) for m in est for v in (m.wx, m.wy, m.wz, m.sx, m.sy, m.sz))


def test_main_replay_writes_one_row_per_sample(tmp_path):
    t = np.arange(30) * 1.0
    rec = tmp_path / "rec.csv"
    write_recording(rec, Recording(t, field(t)))
    out = tmp_path / "rates.csv"
    assert fsw_main.main(["--replay", str(rec), "--rates-out", str(out), "--quiet", "--sigma-uT", "0.1",
                          "--link", "udpout:127.0.0.1:45999"]) == 0
    est = read_rate_estimates(out)
    np.testing.assert_array_equal(est.t_s, t)
    assert np.all(np.isnan(est.w_radps[0])) and np.all(np.isfinite(est.w_radps[1:]))
    np.testing.assert_allclose(est.w_radps[-1], W, atol=math.radians(0.1))
