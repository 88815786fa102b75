"""The flown rate filter in the composed flight software (fsw.system.build_flight, as on target and in
SITL): configured by RunConfig.rate_filter / --rate-filter, the fixed-field filter until the field along
the orbit is on board and the host calibration applied, then the orbit filter; its attitude out as
ATTITUDE_QUATERNION and DEBRIS_ATTITUDE_SIGMA, decoded by ground.decode; the SITL status line."""
import io
import math

import numpy as np
import pytest

from fsw import main as fsw_main
from fsw.config import RunConfig
from fsw.estimation.flown_filter import CalibratedField, FlownFilter
from fsw.system import NullLink, build_flight
from fsw.telemetry.dialect import mavlink
from fsw.timeorbit import TimeOrbit
from ground.decode import Decoder
from hil import sitl
from support import Capture, StubSource, flight_assumptions

pytestmark = pytest.mark.sitl


def test_the_target_flies_the_configured_filter_on_its_onboard_field(tmp_path):
    """fsw.main's options: --rate-filter (default euler) reaches the RunConfig; build_flight flies it on the
    time-and-orbit application's field behind the host calibration."""
    cfg, *_ = fsw_main.parse_args(["--mag-serial", "/dev/null", "--quiet"])
    assert cfg.rate_filter == "euler"
    cfg, *_ = fsw_main.parse_args(["--mag-serial", "/dev/null", "--rate-filter", "mm", "--quiet"])
    assert cfg.rate_filter == "mm"
    timeorbit = TimeOrbit()
    flight = build_flight(cfg, StubSource(1.0), sigma_b_T=1e-6, sample_rate_hz=1.0, link=NullLink(),
                          timeorbit=timeorbit)
    try:
        kf = flight.fsw.estimators["kalman"]
        assert isinstance(kf, FlownFilter) and kf.kind == "mm"
        assert isinstance(kf.provider, CalibratedField) and kf.provider.provider is timeorbit
        assert any("rate filter: mm" in n for n in flight.notes)
        for k in range(200):  # no UTC, no TLE: the fixed-field filter, and it says why
            flight.fsw.tick(0.02 * k)
        assert kf.name == "fixed" and kf.why == "no orbit/field model on board (no TLE on board)"
        assert kf.attitude() is None and kf.handovers == 0
    finally:
        flight.close()


def test_an_unknown_filter_is_a_usage_error(capsys):
    with pytest.raises(SystemExit) as e:
        fsw_main.parse_args(["--mag-serial", "/dev/null", "--rate-filter", "best"])
    assert e.value.code == 2
    assert "--rate-filter" in capsys.readouterr().err


@pytest.mark.slow
def test_sitl_hands_over_sends_the_attitude_and_the_ground_decodes_it():
    """400 s of the shipped cubesat (no host iron; the calibration on board applies its first solution
    after ~200 s): the fixed-field filter, then the Euler filter with the field along the orbit, its rate
    against the truth, ATTITUDE_QUATERNION and DEBRIS_ATTITUDE_SIGMA on the link from the hand-over on."""
    cap = Capture()
    out = io.StringIO()
    cfg = sitl.SitlConfig(run=RunConfig(speed=0.0, duration_s=400.0), scenario=flight_assumptions("isoi"), seed=0)
    run = sitl.run(cfg, out=out, link=cap, ident=False)
    kf = run.fsw.estimators["kalman"]
    assert kf.name == "euler" and kf.handovers == 1 and kf.fallbacks == 0
    text = out.getvalue() + sitl.summary(run)
    assert "fixed→euler" in text and "  euler  w_est=" in text and "att_err=" in text
    msgs = cap.messages()
    sig = [m for m in msgs if m.get_type() == "DEBRIS_ATTITUDE_SIGMA"]
    att = [m for m in msgs if m.get_type() == "ATTITUDE_QUATERNION"]
    filters = [m.filter for m in sig]
    k = filters.index(mavlink.DEBRIS_RATE_FILTER_EULER)
    assert set(filters[:k]) == {mavlink.DEBRIS_RATE_FILTER_FIXED}
    assert set(filters[k:]) == {mavlink.DEBRIS_RATE_FILTER_EULER}
    assert all(math.isnan(x) for m in sig[:k] for x in m.attitude_sigma)
    assert len(att) == len(sig) - k and sig[-1].handovers == 1
    t_handover = sig[k].time_usec * 1e-6
    assert 100.0 < t_handover < 350.0
    # the last minute: the flown rate against the truth, and the quaternion is a unit one
    est = {m.time_usec: (m.wx, m.wy, m.wz) for m in msgs
           if m.get_type() == "DEBRIS_RATE_ESTIMATE" and m.method == mavlink.DEBRIS_RATE_METHOD_KALMAN}
    truth = {m.time_usec: (m.wx, m.wy, m.wz) for m in msgs if m.get_type() == "DEBRIS_SIM_STATE"}
    late = [t for t in est if t * 1e-6 > 340.0 and t in truth]
    err = [np.linalg.norm(np.subtract(est[t], truth[t])) for t in late]
    assert len(late) > 50 and math.degrees(math.sqrt(np.mean(np.square(err)))) < 0.5
    q = att[-1]
    assert abs(math.hypot(q.q1, q.q2, q.q3, q.q4) - 1.0) < 1e-5
    dec = Decoder()
    for m in msgs:
        dec.handle(m, 0.0)
    summary = dec.summary_text()
    assert "flown rate filter: euler (1 hand-overs" in summary and f"{len(att)} ATTITUDE_QUATERNION" in summary
    assert dec.attitude["q_body_to_eci"] == pytest.approx((q.q1, q.q2, q.q3, q.q4))
