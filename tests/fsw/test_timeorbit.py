"""Time and orbit on board through the uplink: signed SYSTEM_TIME sets the UTC, a signed TLE is staged
and loaded with the right MAV_RESULT for each refusal, counted; the TLE survives a restart; what needs
the orbit (the identification experiment) refuses without it and accepts with it."""
import math

import numpy as np
import pytest

from fsw.estimation.tle import parse_tle
from fsw.flight import FlightSoftware
from fsw.ident import TUG, AnnouncedTug, IdentExperiment
from fsw.telemetry.dialect import FSW_COMPID, FSW_SYSID, mavlink
from fsw.telemetry.signing import SigningClock, unix_to_timestamp
from fsw.telemetry.telemetry import Telemetry
from fsw.timeorbit import TimeOrbit, tle_crc
from ground.command import GroundLink
from hil.faults import FaultyLink
from support import StubSource, circular_tle

KEY = bytes(range(7, 39))
T0 = unix_to_timestamp(1_750_000_000.0)
R = mavlink
L1, L2 = circular_tle(485.0, 97.5, epoch="26120.50000000")   # epoch 2026-04-30T12:00:00Z
EPOCH = parse_tle(L1, L2).epoch_utc_s
DAY = 86400.0


class Box:
    """The flight software with the time/orbit application and the identification experiment on an
    in-memory link; a ground station at the other end."""

    def __init__(self, key=KEY, tle_file=None, max_age_d=14.0):
        self.link = FaultyLink(np.random.default_rng(0), src_system=FSW_SYSID, src_component=FSW_COMPID)
        tlm = Telemetry(self.link, key=key, clock=SigningClock(epoch=T0, clock_set=True))
        self.to = TimeOrbit(tle_file=tle_file, max_tle_age_d=max_age_d)
        self.ident = IdentExperiment(sigma_b_T=1e-7, b_inertial=self.to, tug=AnnouncedTug())
        self.fsw = FlightSoftware(StubSource(1.0), tlm, rate_hz=10, sigma_b_T=1e-7, sample_rate_hz=1.0,
                                  uplink=self.link, key=key, apps=[self.to, self.ident])
        self.ground = GroundLink(self.link.ground_write, key, SigningClock(epoch=T0, clock_set=True))
        self.k = 100  # loop time starts at 10 s (a monotonic clock is not UTC)
        self.received = []

    @property
    def now(self):
        return self.k / 10

    def run(self, seconds):
        for _ in range(int(round(seconds * 10))):
            self.fsw.tick(self.now)
            self.k += 1
            self.received += self.ground.feed(self.link.ground_read(), self.now)

    def send_time(self, utc_s, ground=None):
        (ground or self.ground).send(R.MAVLink_system_time_message(int(round(utc_s * 1e6)), 0), self.now)
        self.run(0.2)

    def send_tle(self, l1, l2, crc=None, ground=None):
        g = ground or self.ground
        g.send(R.MAVLink_debris_tle_message(FSW_SYSID, FSW_COMPID, l1.encode("latin-1"), l2.encode("latin-1")),
               self.now)
        g.command_long(R.MAV_CMD_DEBRIS_TLE_LOAD, [float(tle_crc(l1, l2) if crc is None else crc)], self.now)
        self.run(0.3)
        acks = [r.msg.result for r in self.received if r.msg.get_type() == "COMMAND_ACK"
                and r.msg.command == R.MAV_CMD_DEBRIS_TLE_LOAD]
        return acks[-1] if acks else None

    def start_ident(self):
        self.ground.command_long(R.MAV_CMD_DEBRIS_IDENT_START, [TUG, 10, 5, 10, 1.0, 0, 0], self.now)
        self.run(0.3)
        return [r.msg.result for r in self.received if r.msg.get_type() == "COMMAND_ACK"
                and r.msg.command == R.MAV_CMD_DEBRIS_IDENT_START][-1]

    def last(self, kind):
        return [r.msg for r in self.received if r.msg.get_type() == kind][-1]


def fix(line):
    from fsw.estimation.tle import checksum
    return line[:68] + str(checksum(line))


def test_signed_time_sets_the_onboard_utc_and_it_is_reported():
    box = Box()
    box.run(1.0)
    st = box.last("DEBRIS_TIME_ORBIT")
    assert st.utc_usec == 0 and st.tle_state == R.DEBRIS_TLE_STATE_NONE and math.isnan(st.time_set_age)
    utc_at_set = EPOCH + 3600.0
    t_set = box.now
    box.send_time(utc_at_set)
    box.run(2.0)
    st, sys_time = box.last("DEBRIS_TIME_ORBIT"), box.last("SYSTEM_TIME")
    # the box's UTC runs on from the set with its loop time (the set is taken at the tick that reads it)
    assert st.time_sets == 1 and st.field_degree >= 1
    assert abs(st.utc_usec * 1e-6 - (utc_at_set + st.time_usec * 1e-6 - t_set)) < 0.25
    assert abs(sys_time.time_unix_usec * 1e-6 - (utc_at_set + sys_time.time_boot_ms * 1e-3 - t_set)) < 0.25


def test_unsigned_time_and_tle_are_refused_and_counted():
    box = Box()                                   # with a key: the uplink drops them, counted as unsigned
    stranger = GroundLink(box.link.ground_write, None)
    box.send_time(EPOCH + 10.0, ground=stranger)
    assert box.send_tle(L1, L2, ground=stranger) is None
    box.run(1.0)
    assert not box.to.clock.known and box.to.tle is None
    assert box.last("DEBRIS_LINK_STATUS").rejected_unsigned == 3
    nokey = Box(key=None)                         # without a key: handed over unauthenticated, refused here
    nokey.send_time(EPOCH + 10.0)
    assert nokey.send_tle(L1, L2) == R.MAV_RESULT_DENIED   # the router: unauthenticated
    nokey.run(1.0)
    st = nokey.last("DEBRIS_TIME_ORBIT")
    assert not nokey.to.clock.known and nokey.to.tle is None
    assert st.time_refused == 1 and st.tle_refused == 1 and st.tle_last_refusal == R.DEBRIS_TLE_REFUSAL_UNSIGNED


def test_each_bad_tle_gets_its_mav_result_and_is_counted():
    box = Box(max_age_d=3.0)
    assert box.send_tle(L1, L2) == R.MAV_RESULT_TEMPORARILY_REJECTED        # no time yet
    reasons = [box.to.last_refusal]
    box.send_time(EPOCH + 1 * DAY)
    future = circular_tle(485.0, 97.5, epoch="26122.50000000")             # two days after the onboard UTC
    old = circular_tle(485.0, 97.5, epoch="26115.50000000")                # 6 days old, limit 3
    cases = [((L1[:-1] + str((int(L1[-1]) + 1) % 10), L2), None),         # bad checksum
             ((L1, L2[:-2]), None),                                        # 67 characters
             (future, None), (old, None),
             ((L1, L2), 12345)]                                            # CRC of other lines
    for (l1, l2), crc in cases:
        assert box.send_tle(l1, l2, crc=crc) == R.MAV_RESULT_DENIED
        reasons.append(box.to.last_refusal)
    assert reasons == [R.DEBRIS_TLE_REFUSAL_NO_TIME, R.DEBRIS_TLE_REFUSAL_CHECKSUM, R.DEBRIS_TLE_REFUSAL_FORMAT,
                       R.DEBRIS_TLE_REFUSAL_FUTURE_EPOCH, R.DEBRIS_TLE_REFUSAL_TOO_OLD,
                       R.DEBRIS_TLE_REFUSAL_NOT_STAGED]
    assert box.to.tle is None
    box.run(1.0)
    assert box.last("DEBRIS_TIME_ORBIT").tle_refused == 6
    assert box.send_tle(L1, L2) == R.MAV_RESULT_ACCEPTED
    box.run(1.0)
    st = box.last("DEBRIS_TIME_ORBIT")
    assert st.tle_state == R.DEBRIS_TLE_STATE_OK and st.tle_loaded == 1 and st.tle_persisted == 0
    assert st.tle_epoch_usec == int(round(EPOCH * 1e6)) and abs(st.tle_age - DAY) < 5.0


def test_identification_refused_without_orbit_accepted_with_it_and_refused_when_stale():
    box = Box(max_age_d=3.0)
    assert box.start_ident() == R.MAV_RESULT_DENIED
    assert "no TLE on board" in box.fsw.commands.counters.last_error
    box.send_time(EPOCH + 0.5 * DAY)
    assert box.start_ident() == R.MAV_RESULT_DENIED
    assert box.send_tle(L1, L2) == R.MAV_RESULT_ACCEPTED
    assert box.start_ident() == R.MAV_RESULT_ACCEPTED
    # the experiment's field is the onboard one: IGRF along the TLE's orbit at the onboard UTC
    f, why = box.to.field_now(box.now)
    assert why == "" and box.ident._b_fit is f and 15e-6 < np.linalg.norm(f(box.now)) < 60e-6
    box.ground.command_long(R.MAV_CMD_DEBRIS_IDENT_STOP, [], box.now)
    box.run(0.3)
    # three days later by the ground's clock (the box's clock agrees): the TLE is stale, refused again
    box.send_time(EPOCH + 0.5 * DAY + 3 * DAY)
    box.run(1.0)
    assert box.last("DEBRIS_TIME_ORBIT").tle_state == R.DEBRIS_TLE_STATE_STALE
    assert box.start_ident() == R.MAV_RESULT_DENIED and "older" in box.fsw.commands.counters.last_error
    # the age limit is a parameter: raised, the same TLE flies again
    box.ground.send(R.MAVLink_param_set_message(FSW_SYSID, FSW_COMPID, b"TLE_MAX_AGE_D", 7.0,
                                                R.MAV_PARAM_TYPE_REAL32), box.now)
    box.run(0.3)
    assert box.to.max_tle_age_s == 7 * DAY and box.start_ident() == R.MAV_RESULT_ACCEPTED


def test_the_tle_survives_a_restart(tmp_path):
    path = tmp_path / "tle.txt"
    box = Box(tle_file=path)
    assert any("none yet" in n for n in box.to.notes)
    box.send_time(EPOCH + 3600.0)
    assert box.send_tle(L1, L2) == R.MAV_RESULT_ACCEPTED
    assert path.read_text() == f"{L1}\n{L2}\n" and not list(tmp_path.glob(".*tmp"))
    again = Box(tle_file=path)                   # a new flight software reading the file
    assert again.to.tle == box.to.tle and again.to.tle_persisted
    again.run(1.0)
    assert again.last("DEBRIS_TIME_ORBIT").tle_state == R.DEBRIS_TLE_STATE_NO_TIME  # the time is lost in a restart
    assert again.start_ident() == R.MAV_RESULT_DENIED
    again.send_time(EPOCH + 7200.0)
    assert again.start_ident() == R.MAV_RESULT_ACCEPTED


@pytest.mark.parametrize("content", ["garbage\n", f"{L1}\n", f"{L1[:-1]}{(int(L1[-1]) + 1) % 10}\n{L2}\n"])
def test_a_bad_tle_file_is_said_and_not_used(tmp_path, content):
    path = tmp_path / "tle.txt"
    path.write_text(content)
    to = TimeOrbit(tle_file=path)
    assert to.tle is None and any("not a valid TLE" in n for n in to.notes)
    assert path.read_text() == content           # left as it was until a good TLE replaces it


def test_a_composition_presets_time_and_tle_through_the_same_checks():
    to = TimeOrbit(max_tle_age_d=3.0)
    assert to.preset(0.0, EPOCH + 5 * DAY, L1, L2) == R.MAV_RESULT_DENIED          # too old for the limit
    assert to.last_refusal == R.DEBRIS_TLE_REFUSAL_TOO_OLD and to.tle is None
    assert to.preset(0.0, EPOCH + 1 * DAY, L1, L2) == R.MAV_RESULT_ACCEPTED
    assert to.tle_state(10.0) == R.DEBRIS_TLE_STATE_OK and to.field_now(10.0)[0] is not None


def test_the_field_models_coefficients_are_read_before_the_loop():
    from fsw.estimation import igrf
    igrf._COEFFS = None
    TimeOrbit()
    assert igrf._COEFFS is not None


def test_a_time_before_2020_is_refused():
    box = Box()
    box.send_time(0.0)
    box.send_time(1_000_000_000.0)
    assert not box.to.clock.known and box.to.time_refused == 2


def test_a_tle_that_cannot_be_kept_is_still_flown_and_the_failure_said(tmp_path):
    box = Box(tle_file=tmp_path / "missing-dir" / "tle.txt")
    box.send_time(EPOCH + 60.0)
    assert box.send_tle(L1, L2) == R.MAV_RESULT_ACCEPTED
    assert box.to.persist_errors == 1 and not box.to.tle_persisted and "not kept" in box.to.last_error


def test_the_ack_says_why_and_timesync_answers_with_the_onboard_utc():
    box = Box()
    box.send_tle(L1, L2)
    ack = [r.msg for r in box.received if r.msg.get_type() == "COMMAND_ACK"][-1]
    assert (ack.result, ack.result_param2) == (R.MAV_RESULT_TEMPORARILY_REJECTED, R.DEBRIS_TLE_REFUSAL_NO_TIME)
    # TIMESYNC before a time set: the loop time in ns; after: the onboard UTC, ts1 mirrored
    box.ground.send(R.MAVLink_timesync_message(0, 123), box.now)
    box.run(0.2)
    first = box.last("TIMESYNC")
    assert first.ts1 == 123 and abs(first.tc1 * 1e-9 - box.now) < 0.3
    box.send_time(EPOCH + 100.0)
    t_set = box.now - 0.2
    box.ground.send(R.MAVLink_timesync_message(0, 456), box.now)
    box.run(0.2)
    ts = box.last("TIMESYNC")
    assert ts.ts1 == 456 and abs(ts.tc1 * 1e-9 - (EPOCH + 100.0 + box.now - t_set)) < 0.3
    box.send_time(EPOCH + 200.0)
    assert box.send_tle(L1, L2) == R.MAV_RESULT_ACCEPTED
    ack = [r.msg for r in box.received if r.msg.get_type() == "COMMAND_ACK"][-1]
    assert ack.result_param2 == 0


def test_the_drift_of_the_box_clock_from_successive_sets_is_reported():
    from types import SimpleNamespace
    to = TimeOrbit()
    drift = 40e-6                                    # the box's clock runs 40 ppm fast
    for k in range(6):                               # a set every 20 min of true time
        utc = EPOCH + 1200.0 * k
        mono = 50.0 + 1200.0 * k * (1 + drift)
        to.on_system_time(SimpleNamespace(time_unix_usec=int(utc * 1e6)), mono, True)
    f = to.message_fields(50.0 + 7200.0 * (1 + drift))
    # UTC = mono / (1 + drift): the estimator sees UTC − mono shrink by 40 ppm of the box's time
    assert f["drift_ppm"] == pytest.approx(-drift / (1 + drift) * 1e6, abs=0.01)
    assert f["utc_usec"] * 1e-6 == pytest.approx(EPOCH + 7200.0, abs=1e-3)
    assert f["time_sets"] == 6 and abs(f["last_set_residual"]) < 0.05


def test_the_box_sends_the_tle_in_force_when_loaded_and_every_minute(tmp_path):
    box = Box(tle_file=tmp_path / "tle.txt")
    box.run(1.0)
    assert not [r for r in box.received if r.msg.get_type() == "DEBRIS_TLE"]      # none on board: none sent
    box.send_time(EPOCH + 3600.0)
    assert box.send_tle(L1, L2) == R.MAV_RESULT_ACCEPTED
    box.run(125.0)
    sent = [r.msg for r in box.received if r.msg.get_type() == "DEBRIS_TLE"]
    assert len(sent) == 3                                   # at once, then at 60 s and 120 s
    assert all((m.line1, m.line2, m.target_system) == (L1, L2, 0) for m in sent)
    again = Box(tle_file=tmp_path / "tle.txt")              # read back from its file after a restart: said at once
    again.run(1.0)
    assert [(m.msg.line1, m.msg.line2) for m in again.received if m.msg.get_type() == "DEBRIS_TLE"] == [(L1, L2)]


def test_a_field_model_outside_its_span_is_counted_refused_to_its_users_and_in_the_summary():
    """A TLE and a UTC after IGRF-14's span (2030): the field along the orbit cannot be built; whatever asks
    for it is refused with the reason, and the run's summary line says how often and why."""
    l1, l2 = circular_tle(485.0, 97.5, epoch="31120.50000000")   # 2031-04-30
    box = Box()
    box.send_time(parse_tle(l1, l2).epoch_utc_s + 3600.0)
    assert box.send_tle(l1, l2) == R.MAV_RESULT_ACCEPTED
    box.run(1.0)
    field, why = box.to.field_now(box.now)
    assert field is None and "2030" in why, why
    assert box.start_ident() == R.MAV_RESULT_DENIED
    line = box.to.summary_line(box.now)
    assert box.to.field_errors >= 1 and f"; {box.to.field_errors} field errors (last: field model:" in line, line
