"""ground.decode keeps the flown filter's attitude (ATTITUDE_QUATERNION) and its 1-σ (DEBRIS_ATTITUDE_SIGMA)
and reports them; a quaternion that is not finite is refused and counted."""
import math

import numpy as np
import pytest

from fsw.telemetry.dialect import mavlink
from fsw.telemetry.telemetry import Telemetry
from ground.decode import Decoder
from support import Capture

pytestmark = pytest.mark.ground


def sent(*calls):
    cap = Capture()
    tlm = Telemetry(cap)
    for kwargs in calls:
        tlm.attitude(**kwargs)
    return cap.messages()


def test_the_flown_filter_and_its_attitude_are_decoded_and_reported():
    q = np.array([0.5, 0.5, -0.5, 0.5])
    msgs = sent(dict(t_s=10.0, q=None, omega_radps=np.zeros(3), sigma_att_rad=None, sigma_radps=np.full(3, 0.1),
                     filter_id=mavlink.DEBRIS_RATE_FILTER_FIXED, flags=0, handovers=0),
                dict(t_s=11.0, q=q, omega_radps=np.radians([5.0, -3.0, 2.0]), sigma_att_rad=np.radians([1.0, 2.0, 3.0]),
                     sigma_radps=np.radians([0.1, 0.2, 0.3]), filter_id=mavlink.DEBRIS_RATE_FILTER_EULER, flags=0,
                     handovers=1))
    assert [m.get_type() for m in msgs] == ["DEBRIS_ATTITUDE_SIGMA", "ATTITUDE_QUATERNION", "DEBRIS_ATTITUDE_SIGMA"]
    assert all(math.isnan(x) for x in msgs[0].attitude_sigma)
    assert msgs[1].time_boot_ms == 11000 and msgs[1].rollspeed == pytest.approx(math.radians(5.0))
    dec = Decoder()
    for m in msgs:
        dec.handle(m, 0.0)
    a = dec.attitude
    assert a["filter"] == "euler" and a["handovers"] == 1 and a["q_body_to_eci"] == pytest.approx(tuple(q))
    assert np.degrees(a["sigma_att_rad"]) == pytest.approx([1.0, 2.0, 3.0], rel=1e-6)
    text = dec.summary_text()
    assert "flown rate filter: euler (1 hand-overs from the fixed-field filter), 1 ATTITUDE_QUATERNION" in text
    assert "1-σ (1.00 2.00 3.00) deg" in text and "rate 1-σ (0.10 0.20 0.30) deg/s" in text


def test_a_quaternion_that_is_not_finite_is_refused_and_counted():
    cap = Capture()
    cap.mav.send(mavlink.MAVLink_attitude_quaternion_message(1000, math.nan, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0,
                                                            [0.0] * 4))
    dec = Decoder()
    for m in cap.messages():
        dec.handle(m, 0.0)
    assert dec.invalid["ATTITUDE_QUATERNION"] == 1 and "q_body_to_eci" not in dec.attitude
