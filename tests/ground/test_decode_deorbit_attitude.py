"""DEBRIS_DEORBIT_ATTITUDE (the de-orbit controller's inputs) from the kit's report through the link to
ground.decode, in SI; an unknown source value is refused and counted."""
import math


import pytest

from fsw.deorbit.onboard_attitude import AttitudeReport
from fsw.telemetry.dialect import mavlink
from fsw.telemetry.telemetry import Telemetry
from ground.decode import Decoder
from support import Capture

pytestmark = pytest.mark.ground


def test_the_controller_inputs_round_trip_to_the_ground():
    cap = Capture()
    tlm = Telemetry(cap)
    rep = AttitudeReport(0.1, -0.05, 2.5, (1e-4, -2e-4, 3e-4), (0.02, 0.03), 5e-5,
                         mavlink.DEBRIS_CONTROLLER_ATTITUDE_TRUSTED, 1)
    tlm.deorbit_attitude(12.5, rep, held=9)
    tlm.deorbit_attitude(13.5, AttitudeReport(), held=10)  # no estimate yet: NaN, source NONE
    dec = Decoder()
    msgs = cap.messages()
    assert [m.get_type() for m in msgs] == ["DEBRIS_DEORBIT_ATTITUDE"] * 2
    dec.handle(msgs[0], 0.0)
    a = dec.deorbit_attitude
    assert a["t_s"] == pytest.approx(12.5) and a["source"] == "trusted" and a["held"] == 9
    assert (a["yaw_rad"], a["pitch_rad"], a["roll_rad"]) == pytest.approx((0.1, -0.05, 2.5), rel=1e-6)
    assert a["rate_radps"] == pytest.approx((1e-4, -2e-4, 3e-4), rel=1e-6)
    assert a["pointing_sigma_rad"] == pytest.approx((0.02, 0.03), rel=1e-6)
    assert a["rate_sigma_radps"] == pytest.approx(5e-5, rel=1e-6) and a["hypotheses"] == 1
    dec.handle(msgs[1], 0.0)
    a = dec.deorbit_attitude
    assert a["source"] == "none" and a["held"] == 10 and math.isnan(a["yaw_rad"])
    assert all(math.isnan(x) for x in a["rate_radps"])


def test_an_unknown_source_is_refused_and_counted():
    cap = Capture()
    cap.mav.send(mavlink.MAVLink_debris_deorbit_attitude_message(1000, 0.0, 0.0, 0.0, [0.0] * 3, [0.0] * 2, 0.0,
                                                                 200, 0, 0))
    dec = Decoder()
    for m in cap.messages():
        dec.handle(m, 0.0)
    assert dec.invalid["DEBRIS_DEORBIT_ATTITUDE"] == 1 and dec.deorbit_attitude == {}
