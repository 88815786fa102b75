"""The flight software's task table with a stubbed field source and a captured link."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fsw.estimation import rate_formulas as rf
from fsw.flight import FlightSoftware
from fsw.telemetry.dialect import FSW_SYSID, mavlink
from fsw.telemetry.telemetry import Telemetry
from support import B_I_T, Capture, StubSource, W_RADPS

def run(seconds, rate_hz=50.0, sample_period_s=0.1, **kw):
    link = Capture()
    fsw = FlightSoftware(StubSource(sample_period_s), Telemetry(link), rate_hz=rate_hz, sigma_b_T=0.05e-6,
                         sample_rate_hz=1 / sample_period_s, **kw)
    for k in range(int(round(seconds * rate_hz))):
        fsw.tick(k / rate_hz)
    return fsw, link.messages()


def by_type(msgs, name):
    return [m for m in msgs if m.get_type() == name]


def test_message_rates_and_contents():
    fsw, msgs = run(5.0)
    assert len(by_type(msgs, "HEARTBEAT")) == 5
    hb = by_type(msgs, "HEARTBEAT")[0]
    assert hb.type == mavlink.MAV_TYPE_SPACECRAFT_ORBITER and hb.autopilot == mavlink.MAV_AUTOPILOT_GENERIC
    assert len(by_type(msgs, "SYS_STATUS")) == 5
    assert len(by_type(msgs, "DEBRIS_LOOP_STATUS")) == 5
    imu = by_type(msgs, "DEBRIS_MAG_SAMPLE")
    assert len(imu) == 50
    assert [m.seq for m in imu] == list(range(50)) and all(m.flags == 0 for m in imu)   # numbered, live
    np.testing.assert_allclose(imu[3].mag, Rotation.from_rotvec(-W_RADPS * 0.3).apply(B_I_T) * 1e4, rtol=1e-6)
    assert imu[3].time_usec == 300_000
    store = by_type(msgs, "DEBRIS_SAMPLE_STORE")
    assert len(store) == 5 and store[-1].next_seq == 41 and store[-1].stored_first_seq == 0   # at t = 4 s
    assert all(m.get_header().srcSystem == FSW_SYSID for m in msgs)
    est = by_type(msgs, "DEBRIS_RATE_ESTIMATE")
    boer = [m for m in est if m.method == mavlink.DEBRIS_RATE_METHOD_BOER]
    deriv = [m for m in est if m.method == mavlink.DEBRIS_RATE_METHOD_DERIVATIVE]
    assert len(boer) == 49 and len(deriv) == 48
    # the derivative formula on a constant-rate body: sin(θ)/Δt ω̂ (tests/test_rate_formulas.py)
    wn = np.linalg.norm(W_RADPS)
    expected = np.sin(wn * 0.1) / 0.1 * W_RADPS / wn
    np.testing.assert_allclose([deriv[-1].wx, deriv[-1].wy, deriv[-1].wz], expected, rtol=1e-5)
    assert boer[-1].flags == mavlink.DEBRIS_ESTIMATE_FLAGS_PERPENDICULAR_ONLY
    assert all(np.isfinite([m.sx, m.sy, m.sz]).all() and m.sx > 0 for m in est)


def test_sample_telemetry_is_decimated_to_the_link_budget():
    fsw, msgs = run(2.0, rate_hz=100.0, sample_period_s=0.01, max_sample_tlm_hz=20.0)
    assert fsw.samples == 200
    imu = by_type(msgs, "DEBRIS_MAG_SAMPLE")
    assert len(imu) == 40
    assert np.diff([m.time_usec for m in imu]) == pytest.approx(50_000)


def test_link_errors_are_counted_not_raised():
    class Broken(Capture):
        def write(self, b):
            raise OSError("port gone")

    link = Broken()
    fsw = FlightSoftware(StubSource(0.1), Telemetry(link), rate_hz=50, sigma_b_T=1e-7)
    for k in range(100):
        fsw.tick(k / 50)
    assert fsw.tlm.send_errors > 0 and fsw.tlm.frames_sent == 0
    assert fsw.samples == 20
    assert fsw.scheduler.stats.ticks == 100


def test_estimator_matches_pure_function_on_the_same_samples():
    fsw, msgs = run(3.0)
    imu = by_type(msgs, "DEBRIS_MAG_SAMPLE")
    t = np.array([m.time_usec for m in imu]) * 1e-6
    b = np.array([m.mag for m in imu]) * 1e-4
    boer = [m for m in by_type(msgs, "DEBRIS_RATE_ESTIMATE") if m.method == mavlink.DEBRIS_RATE_METHOD_BOER]
    np.testing.assert_allclose([[m.wx, m.wy, m.wz] for m in boer], rf.boer_rate(t, b)[1:], rtol=1e-4,
                               atol=1e-6)


def test_counters_past_2_to_the_32_go_out_wrapped_and_the_messages_keep_coming():
    """A loop at 1 kHz counts past 2³² ticks in 50 days, a 1 kHz sensor past 2³² samples too: the uint32
    fields carry them modulo 2³² (as MAVLink's own counters do), the frames
    are never refused by the encoder."""
    from types import SimpleNamespace

    link = Capture()
    tlm = Telemetry(link)
    big = 2**32 + 7
    tlm.loop_status(1.0, ticks=big, overruns=big + 1, task_overruns=2**33 + 2, period_s=0.02, mean_us=1.0,
                    p50_us=1.0, p99_us=1.0, max_us=1.0)
    driver = SimpleNamespace(offset_T=np.zeros(3), samples=big, bus_errors=big + 1, timeouts=big + 2,
                             bad_id=big + 3, resets=70000, state=3, offset_jumps=0, offset_outliers=0,
                             offset_disturbed=0)
    tlm.mag_status(1.0, driver)
    loop, = by_type(link.messages(), "DEBRIS_LOOP_STATUS")
    mag, = by_type(link.messages(), "DEBRIS_MAG_STATUS")
    assert (loop.ticks, loop.overruns, loop.task_overruns) == (7, 8, 2)
    assert (mag.samples, mag.bus_errors, mag.timeouts, mag.bad_id, mag.resets) == (7, 8, 9, 10, 65535)
    assert tlm.encode_errors == 0
